# TopoFusion service image: `docker build -t topofusion .`
# Build stage: install the package and its dependencies into a prefix.
FROM python:3.11-slim AS build
WORKDIR /src
COPY pyproject.toml README.md ./
COPY service ./service
RUN pip install --no-cache-dir --prefix=/install .

# Run stage: slim, non-root, exec-form entrypoint so SIGTERM reaches the process.
FROM python:3.11-slim
RUN groupadd --system --gid 10001 topofusion \
    && useradd --system --uid 10001 --gid 10001 --home-dir /app --no-create-home topofusion \
    && mkdir -p /app \
    && chown 10001:10001 /app
COPY --from=build /install /usr/local
WORKDIR /app
ENV PYTHONUNBUFFERED=1 \
    TOPOFUSION_HTTP_HOST=0.0.0.0 \
    TOPOFUSION_HTTP_PORT=8000 \
    TOPOFUSION_ZENOH_MODE=client
# 8000: HTTP side port; 7447: Zenoh, when run in peer or router mode.
EXPOSE 8000 7447
USER 10001
HEALTHCHECK --interval=10s --timeout=3s --start-period=15s --retries=3 CMD ["topofusion", "healthcheck"]
ENTRYPOINT ["topofusion"]
CMD ["run"]
