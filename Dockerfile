# TopoFusion service image: `docker build -t topofusion .`
# On its own it runs as a Zenoh peer that radars connect to, and serves HTTP:
#   docker run -p 127.0.0.1:8000:8000 -p 7447:7447 topofusion
# Inside the container it listens on every address (tcp/0.0.0.0:7447, 0.0.0.0:8000), which is
# only the container's own network namespace: what `-p` publishes, and on which host address,
# decides what is exposed (above: HTTP to this host only, Zenoh to the network).
# docs/operations/deploy.md: compose, Kubernetes, the token, the state volume.
# Build stage: install the package and its dependencies into a prefix.
FROM python:3.11-slim AS build
WORKDIR /src
COPY pyproject.toml README.md ./
COPY service ./service
RUN pip install --no-cache-dir --prefix=/install .

# Run stage: slim, non-root, exec-form entrypoint so SIGTERM reaches the process.
FROM python:3.11-slim
# /var/lib/topofusion belongs to the service's user: a named volume mounted there starts as a
# copy of it (owner included), so the state is writable without running as root.
RUN groupadd --system --gid 10001 topofusion \
    && useradd --system --uid 10001 --gid 10001 --home-dir /app --no-create-home topofusion \
    && mkdir -p /app /var/lib/topofusion \
    && chown 10001:10001 /app /var/lib/topofusion
COPY --from=build /install /usr/local
WORKDIR /app
# Peer mode on the contract's port: the container runs without a router; compose and the
# Kubernetes manifests make it a client of theirs instead.
# TOPOFUSION_STOP_GRACE_S: Docker's default stop timeout is 10 s; from SIGTERM the worker gets
# this grace to finish its queue, at most 5 s more for the message it is on and the final
# flush, then it publishes its last outputs and writes its state.
ENV PYTHONUNBUFFERED=1 \
    TOPOFUSION_HTTP_HOST=0.0.0.0 \
    TOPOFUSION_HTTP_PORT=8000 \
    TOPOFUSION_ZENOH_MODE=peer \
    TOPOFUSION_ZENOH_LISTEN=tcp/0.0.0.0:7447 \
    TOPOFUSION_STATE_DIR=/var/lib/topofusion \
    TOPOFUSION_STOP_GRACE_S=4
# 8000: HTTP side port; 7447: Zenoh (the peer's listen endpoint above).
EXPOSE 8000 7447
VOLUME ["/var/lib/topofusion"]
USER 10001
STOPSIGNAL SIGTERM
HEALTHCHECK --interval=10s --timeout=3s --start-period=15s --retries=3 CMD ["topofusion", "healthcheck"]
ENTRYPOINT ["topofusion"]
CMD ["run"]
