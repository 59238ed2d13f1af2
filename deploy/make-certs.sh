#!/bin/sh
# Make the certificates of a cfbci deployment with the openssl command line tool.
#
#   deploy/make-certs.sh DIR ROUTER_NAME [ROUTER_NAME ...] [--client CN ...]
#
# Creates, in DIR (made if missing):
#   ca.pem, ca-key.pem          the deployment's certificate authority (kept if present)
#   router.pem, router-key.pem  the router's certificate, valid for every ROUTER_NAME
#                               (host names or IP addresses the clients connect to)
#   CN.pem, CN-key.pem          one client certificate per --client CN (common name CN),
#                               for routers that require client certificates (mutual TLS)
# Keys are ECDSA P-256, certificates valid 825 days. Keep ca-key.pem off the machines:
# only the router needs router-key.pem, and each client only its own key.
set -eu

usage() { echo "usage: $0 DIR ROUTER_NAME [ROUTER_NAME ...] [--client CN ...]" >&2; exit 2; }
[ $# -ge 2 ] || usage
dir=$1; shift
mkdir -p "$dir"
umask 077

names=""; clients=""; mode=router
for arg in "$@"; do
    case $arg in
        --client) mode=client ;;
        -*) usage ;;
        *) if [ $mode = router ]; then names="$names $arg"; else clients="$clients $arg"; fi ;;
    esac
done
[ -n "$names" ] || usage

key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1"; }

if [ ! -f "$dir/ca.pem" ]; then
    key "$dir/ca-key.pem"
    openssl req -x509 -new -key "$dir/ca-key.pem" -out "$dir/ca.pem" -days 825 -sha256 \
        -subj "/CN=cfbci deployment CA" \
        -addext "basicConstraints=critical,CA:TRUE" \
        -addext "keyUsage=critical,keyCertSign,cRLSign"
fi

# sign NAME CN EXTENSIONS: NAME.pem and NAME-key.pem, signed by the CA.
sign() {
    key "$dir/$1-key.pem"
    openssl req -new -key "$dir/$1-key.pem" -subj "/CN=$2" -out "$dir/$1.csr"
    printf '%s\n' "basicConstraints=critical,CA:FALSE" \
        "keyUsage=critical,digitalSignature" "$3" > "$dir/$1.ext"
    # A random serial number (no serial file left beside the CA).
    openssl x509 -req -in "$dir/$1.csr" -CA "$dir/ca.pem" -CAkey "$dir/ca-key.pem" \
        -set_serial "0x$(openssl rand -hex 16)" -out "$dir/$1.pem" -days 825 -sha256 \
        -extfile "$dir/$1.ext" 2>/dev/null
    rm -f "$dir/$1.csr" "$dir/$1.ext"
}

san=""
for name in $names; do
    case $name in
        *[!0-9.]*) entry="DNS:$name" ;;  # not only digits and dots: a host name
        *) entry="IP:$name" ;;
    esac
    san="${san:+$san,}$entry"
done
first=$(echo $names | cut -d' ' -f1)
sign router "$first" "extendedKeyUsage=serverAuth
subjectAltName=$san"
for cn in $clients; do
    sign "$cn" "$cn" "extendedKeyUsage=clientAuth"
done
chmod 644 "$dir"/*.pem
chmod 600 "$dir"/*-key.pem
echo "certificates in $dir: $(cd "$dir" && ls ./*.pem | tr '\n' ' ')"
