#!/usr/bin/env bash
# Make a throw-away test CA, a server certificate for HOST and a client certificate, to try
# Zenoh TLS (deploy/zenoh-tls.json5) and mutual TLS.
#
# FOR TESTING ONLY. Production needs real certificates: issued by your organisation's CA (or a
# CA whose key is kept offline), with planned expiry and renewal; never ship these files.
#
#   bash deploy/make-tls-certs.sh HOST[,HOST...] [DIR]
#
# HOST: the listening host's name or IP address exactly as the others write it in
#       `--connect tls/HOST:7447` (it goes into the server certificate's subjectAltName, which
#       Zenoh checks when verify_name_on_connect is true). A router reached at several addresses
#       (one per network) lists them all, comma-separated.
# DIR:  output directory (default: ./wfnn-tls), created if needed. It receives
#       ca.pem ca-key.pem              the CA (keep ca-key.pem off the robot and think hosts)
#       server.pem server-key.pem      robot (listening) side:
#                                      listen_certificate / listen_private_key
#       client.pem client-key.pem      think-server (connecting) side, for mutual TLS:
#                                      connect_certificate / connect_private_key
# Every host needs ca.pem (root_ca_certificate). Keys are EC P-256, PKCS#8, mode 600.
set -euo pipefail
if [ $# -lt 1 ] || [ $# -gt 2 ]; then
  echo "usage: $0 HOST [DIR]" >&2
  exit 2
fi
host=$1
dir=${2:-wfnn-tls}
days=${DAYS:-30}
mkdir -p "$dir"
cd "$dir"
umask 077

# subjectAltName: an IP address entry for an address, a DNS entry otherwise.
san=""
IFS=, read -ra names <<< "$host"
for name in "${names[@]}"; do
  if [[ $name =~ ^[0-9.]+$ || $name == *:* ]]; then entry="IP:$name"; else entry="DNS:$name"; fi
  san="${san:+$san,}$entry"
done

key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1"; }

# cert NAME CN EXTENSIONS [CA options]: a key, then a certificate for it (self-signed without
# CA options).
cert() {
  local name=$1 cn=$2 ext=$3
  shift 3
  local signer=("$@")
  [ $# -gt 0 ] || signer=(-signkey "$name-key.pem")
  key "$name-key.pem"
  openssl req -new -key "$name-key.pem" -subj "/CN=$cn" -out "$name.csr"
  openssl x509 -req -in "$name.csr" "${signer[@]}" -days "$days" -sha256 \
    -set_serial "0x$(openssl rand -hex 16)" -extfile <(printf '%s\n' "$ext") -out "$name.pem"
  rm -f "$name.csr"
}

cert ca "wfnn test CA" "basicConstraints=critical,CA:TRUE
keyUsage=critical,keyCertSign,cRLSign
subjectKeyIdentifier=hash"
cert server "${names[0]}" "basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=serverAuth
subjectAltName=$san" -CA ca.pem -CAkey ca-key.pem
cert client "wfnn-think" "basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=clientAuth" -CA ca.pem -CAkey ca-key.pem

chmod 600 ./*-key.pem
chmod 644 ca.pem server.pem client.pem
openssl verify -CAfile ca.pem server.pem client.pem
echo "wrote $(pwd): ca.pem server.pem server-key.pem client.pem client-key.pem (and ca-key.pem)"
