#!/usr/bin/env bash
# Certificates for deploy/secure/ (mutual TLS between the Zenoh router and its clients).
#
#   make-certs.sh OUT_DIR ROUTER_NAME [SUBJECT ...]
#
# OUT_DIR      where the files go (created if missing; the CA found there is reused).
# ROUTER_NAME  the host name clients connect to (tls/ROUTER_NAME:7447): the router's
#              certificate names it, and clients check that it does. More names or addresses:
#              ROUTER_SANS="DNS:zenoh,IP:10.0.0.5" make-certs.sh ...
# SUBJECT      one client certificate each, its common name the subject (what the router's
#              access control matches in cert_common_names). Default: the subjects of
#              router.json5, topofusion radar-A radar-B operator.
#
# Writes ca.pem and ca.key, router.pem and router.key (each pair once: delete it to make a
# new one), SUBJECT.pem and SUBJECT.key. Run it again with new subjects to add clients, or
# with existing ones to renew them. Keep ca.key off the machines that run Zenoh.
# DAYS (default 365) is how long the router and client certificates last, CA_DAYS (default
# 3650) the CA's.
set -euo pipefail

if [ $# -lt 2 ]; then
  sed -n '3,18p' "$0" | sed 's/^# \{0,1\}//' >&2
  exit 2
fi
out=$1
router=$2
shift 2
if [ $# -eq 0 ]; then
  set -- topofusion radar-A radar-B operator
fi
days=${DAYS:-365}
ca_days=${CA_DAYS:-3650}

for name in "$router" "$@"; do
  # The names become file names and certificate subjects: nothing that needs quoting.
  if ! [[ $name =~ ^[A-Za-z0-9._-]+$ ]]; then
    echo "make-certs.sh: not a plain name: '$name'" >&2
    exit 2
  fi
done
for subject in "$@"; do
  # Their files would overwrite the CA's or the router's.
  if [ "$subject" = ca ] || [ "$subject" = router ]; then
    echo "make-certs.sh: '$subject' cannot be a client subject" >&2
    exit 2
  fi
done

umask 077 # private keys readable by their owner only
mkdir -p "$out"
cd "$out"
ext=$(mktemp)
trap 'rm -f "$ext" ./*.csr' EXIT

# P-256 keys: accepted by rustls (Zenoh's TLS) and quick to make.
new_key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }
# A random 128-bit serial, so that a renewed certificate never repeats an old serial.
serial() { echo "0x$(openssl rand -hex 16)"; }

if [ ! -f ca.key ]; then
  new_key ca.key
  cat >"$ext" <<EOF
[req]
distinguished_name = dn
[dn]
[ca]
basicConstraints = critical, CA:TRUE, pathlen:0
keyUsage = critical, keyCertSign, cRLSign
subjectKeyIdentifier = hash
EOF
  openssl req -x509 -new -key ca.key -sha256 -days "$ca_days" -set_serial "$(serial)" \
    -subj "/CN=TopoFusion Zenoh CA" -config "$ext" -extensions ca -out ca.pem
  echo "new CA: $out/ca.pem"
fi

# issue FILE CN EXTENSIONS: FILE.key and FILE.pem, signed by the CA, common name CN.
issue() {
  new_key "$1.key"
  openssl req -new -key "$1.key" -subj "/CN=$2" -config "$ext" -out "$1.csr"
  openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -set_serial "$(serial)" \
    -days "$days" -sha256 -extfile "$ext" -extensions "$3" -out "$1.pem" 2>/dev/null
  echo "$out/$1.pem (CN=$2)"
}

if [[ $router =~ ^[0-9.]+$ ]]; then
  router_san="IP:$router"
else
  router_san="DNS:$router"
fi
cat >"$ext" <<EOF
[req]
distinguished_name = dn
[dn]
[server]
basicConstraints = critical, CA:FALSE
keyUsage = critical, digitalSignature
extendedKeyUsage = serverAuth
subjectAltName = $router_san${ROUTER_SANS:+,$ROUTER_SANS}
authorityKeyIdentifier = keyid
[client]
basicConstraints = critical, CA:FALSE
keyUsage = critical, digitalSignature
extendedKeyUsage = clientAuth
authorityKeyIdentifier = keyid
EOF

# Kept when it exists: adding a client needs no new router certificate. To renew it (or name
# another host), delete router.pem first.
if [ ! -f router.pem ]; then
  issue router "$router" server
fi
for subject in "$@"; do
  issue "$subject" "$subject" client
done
