#!/bin/sh
# Make a private CA and the certificates of a TLS fleet, for tests and first trials.
#
#   deploy/tls/make-certs.sh DIR ROUTER_NAME [CLIENT_CN ...]
#
# DIR/ca.pem, ca.key         the fleet's certificate authority (keep ca.key offline in production)
# DIR/router.pem, router.key  the router's certificate; its SAN holds ROUTER_NAME, localhost and
#                             127.0.0.1, the names clients verify when they connect
# DIR/<CN>.pem, <CN>.key      one client certificate per robot; its common name is what the
#                             access-control example (deploy/acl/) matches to let a robot publish
# Needs only the openssl command line. Certificates are valid for 30 days.
set -eu
[ $# -ge 2 ] || { echo "usage: $0 DIR ROUTER_NAME [CLIENT_CN ...]" >&2; exit 2; }
dir=$1; router=$2; shift 2
mkdir -p "$dir"
cd "$dir"
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -days 30 \
    -subj "/CN=pgvd fleet test CA" -keyout ca.key -out ca.pem 2>/dev/null
issue() {  # issue NAME CN SAN
    openssl req -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes \
        -subj "/CN=$2" -keyout "$1.key" -out "$1.csr" 2>/dev/null
    printf 'subjectAltName=%s\nbasicConstraints=CA:FALSE\n' "$3" > "$1.ext"
    openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -days 30 \
        -extfile "$1.ext" -out "$1.pem" 2>/dev/null
    rm -f "$1.csr" "$1.ext"
}
issue router "$router" "DNS:$router,DNS:localhost,IP:127.0.0.1"
for cn in "$@"; do
    issue "$cn" "$cn" "DNS:$cn"
done
chmod 600 ./*.key
