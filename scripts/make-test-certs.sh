#!/bin/sh
# Test certificates for Zenoh TLS and mutual TLS between the cubeloc daemon and its
# subscribers: a throw-away certificate authority, a certificate for the daemon and one
# per client name. For tests and bench set-ups only: keys are unencrypted, the CA key sits
# next to the certificates and everything expires in DAYS days. On a robot, use your
# organisation's CA (docs/security.md).
#
#   scripts/make-test-certs.sh OUTDIR [CLIENT_NAME...]     (default client: operator)
#
# OUTDIR gets:
#   ca.pem ca-key.pem               the test CA (root_ca_certificate on both sides)
#   daemon.pem daemon-key.pem       CN=cubeloc-daemon, SAN localhost, 127.0.0.1, ::1
#   <client>.pem <client>-key.pem   CN=<client>, for mutual TLS (connect_certificate)
# Keys are EC P-256 in PKCS#8 (what rustls, and so Zenoh, reads). Needs openssl >= 1.1.1.
set -eu

if [ $# -lt 1 ]; then
    echo "usage: $0 OUTDIR [CLIENT_NAME...]" >&2
    exit 2
fi
out=$1
shift
[ $# -gt 0 ] || set -- operator
for client in "$@"; do
    case $client in
        *[!A-Za-z0-9._-]*|"") echo "$0: client name '$client': use letters, digits, . _ -" >&2; exit 2 ;;
    esac
done
DAYS=${DAYS:-30}
DAEMON_CN=${DAEMON_CN:-cubeloc-daemon}

mkdir -p "$out"
umask 077
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

# leaf NAME CN SAN: a key and a certificate signed by the CA, for server and client use
leaf() {
    name=$1 cn=$2 san=$3
    key "$out/$name-key.pem"
    openssl req -new -key "$out/$name-key.pem" -subj "/O=cubeloc test/CN=$cn" -out "$work/$name.csr"
    cat >"$work/$name.ext" <<EXT
basicConstraints = critical, CA:FALSE
keyUsage = critical, digitalSignature, keyEncipherment
extendedKeyUsage = serverAuth, clientAuth
subjectAltName = $san
EXT
    openssl x509 -req -in "$work/$name.csr" -CA "$out/ca.pem" -CAkey "$out/ca-key.pem" \
        -set_serial "0x$(openssl rand -hex 8)" -days "$DAYS" -sha256 -extfile "$work/$name.ext" \
        -out "$out/$name.pem" 2>/dev/null
}

key "$out/ca-key.pem"
openssl req -new -x509 -key "$out/ca-key.pem" -subj "/O=cubeloc test/CN=cubeloc test CA" \
    -days "$DAYS" -sha256 -addext "basicConstraints=critical,CA:TRUE,pathlen:0" \
    -addext "keyUsage=critical,keyCertSign,cRLSign" -out "$out/ca.pem"

leaf daemon "$DAEMON_CN" "DNS:localhost, DNS:$DAEMON_CN, IP:127.0.0.1, IP:::1"
for client in "$@"; do
    leaf "$client" "$client" "DNS:$client"
done
chmod 0644 "$out"/*.pem
chmod 0600 "$out"/*-key.pem
for cert in "$out"/daemon.pem $(for c in "$@"; do echo "$out/$c.pem"; done); do
    openssl verify -CAfile "$out/ca.pem" "$cert" >/dev/null
done
echo "test certificates in $out: ca.pem, daemon.pem$(for c in "$@"; do printf ', %s.pem' "$c"; done) (valid $DAYS days)"
