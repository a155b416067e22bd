#!/usr/bin/env bash
# Makes development TLS files for vasld with openssl: a self-signed CA, a server certificate for
# localhost / 127.0.0.1 / ::1 (plus any names given with --san), and a client certificate (for
# mutual TLS), all signed by that CA. NOT for production: the CA key sits beside the certificates.
#
#   deploy/make-dev-certs.sh DIR [--days N] [--san DNS:host.example] [--san IP:10.0.0.5] [--force]
#
# Writes into DIR (created, mode 0750):
#   ca.crt ca.key            the CA (clients trust ca.crt; vasld's tls-client-ca for mTLS)
#   server.crt server.key    vasld's tls-cert / tls-key (CN localhost, serverAuth)
#   client.crt client.key    a client certificate (CN vasl-client, clientAuth)
# Keys are EC P-256, mode 0600. Existing files are kept unless --force is given.
set -euo pipefail

usage() { sed -n '2,12p' "$0" | sed 's/^# \{0,1\}//'; exit "${1:-2}"; }

dir=""
days=365
force=0
extra_san=()
while [ "$#" -gt 0 ]; do
  case "$1" in
    --days) days="${2:?--days needs a number}"; shift 2 ;;
    --san) extra_san+=("${2:?--san needs DNS:name or IP:address}"); shift 2 ;;
    --force) force=1; shift ;;
    -h|--help) usage 0 ;;
    -*) echo "make-dev-certs: unknown option $1" >&2; usage ;;
    *) [ -z "$dir" ] || { echo "make-dev-certs: one directory only" >&2; usage; }; dir="$1"; shift ;;
  esac
done
[ -n "$dir" ] || usage
command -v openssl > /dev/null || { echo "make-dev-certs: openssl is missing (apt-get install openssl)" >&2; exit 1; }
case "$days" in ''|*[!0-9]*) echo "make-dev-certs: --days must be a number" >&2; exit 2 ;; esac

if [ "$force" -eq 0 ] && [ -f "$dir/ca.crt" ] && [ -f "$dir/server.crt" ] && [ -f "$dir/client.crt" ]; then
  echo "make-dev-certs: $dir already holds ca.crt, server.crt and client.crt (--force to remake)"
  exit 0
fi
mkdir -p "$dir"
chmod 0750 "$dir"
umask 077
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT

san="DNS:localhost,IP:127.0.0.1,IP:::1"
for s in "${extra_san[@]+"${extra_san[@]}"}"; do san="$san,$s"; done

key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2> /dev/null; }

# The CA.
key "$tmp/ca.key"
openssl req -x509 -new -key "$tmp/ca.key" -sha256 -days "$days" -subj "/CN=vasl development CA" \
  -addext "basicConstraints=critical,CA:TRUE,pathlen:0" \
  -addext "keyUsage=critical,keyCertSign,cRLSign" \
  -addext "subjectKeyIdentifier=hash" -out "$tmp/ca.crt"

# sign NAME CN EXTENSIONS: a key and a CA-signed certificate NAME.key / NAME.crt.
sign() {
  local name="$1" cn="$2" ext="$3"
  key "$tmp/$name.key"
  openssl req -new -key "$tmp/$name.key" -subj "/CN=$cn" -out "$tmp/$name.csr"
  printf '%b\n' "$ext" > "$tmp/$name.ext"
  openssl x509 -req -in "$tmp/$name.csr" -CA "$tmp/ca.crt" -CAkey "$tmp/ca.key" \
    -CAcreateserial -CAserial "$tmp/ca.srl" -sha256 -days "$days" -extfile "$tmp/$name.ext" \
    -out "$tmp/$name.crt" 2> /dev/null
  openssl verify -CAfile "$tmp/ca.crt" "$tmp/$name.crt" > /dev/null
}
sign server localhost "basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature,keyEncipherment\nextendedKeyUsage=serverAuth\nsubjectAltName=$san\nauthorityKeyIdentifier=keyid"
sign client vasl-client "basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature,keyEncipherment\nextendedKeyUsage=clientAuth\nauthorityKeyIdentifier=keyid"

for f in ca server client; do
  install -m 0644 "$tmp/$f.crt" "$dir/$f.crt"
  install -m 0600 "$tmp/$f.key" "$dir/$f.key"
done
echo "make-dev-certs: wrote $dir/{ca,server,client}.{crt,key} (server names: $san; $days days)"
