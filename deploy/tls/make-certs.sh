#!/usr/bin/env bash
# Make a small PKI for the twin's TLS links with openssl:
#   ca.pem/ca.key             the certificate authority (keep ca.key offline)
#   twin.pem/twin.key         the twin's (or router's) server certificate, valid for the names given
#   <CN>.pem/<CN>.key         one client certificate per common name (default: operator viewer recorder)
#
#   deploy/tls/make-certs.sh OUT_DIR "twin-host.martian,localhost,127.0.0.1" [CN ...]
#
# Then install on the twin host: ca.pem, twin.pem, twin.key (mode 600, owner twind) in
# /etc/twind/tls/; on each client: ca.pem, and its <CN>.pem/<CN>.key as client.pem/client.key.
# Certificates are valid for DAYS days (default 825); keys are ECDSA P-256.
set -euo pipefail
out=${1:?usage: make-certs.sh OUT_DIR NAMES [CN ...]}
names=${2:?usage: make-certs.sh OUT_DIR NAMES [CN ...] (NAMES: comma-separated DNS names or IPs)}
shift 2
cns=("$@")
[ ${#cns[@]} -gt 0 ] || cns=(operator viewer recorder)
days=${DAYS:-825}
mkdir -p "$out"
cd "$out"
umask 077

key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

san=""
IFS=',' read -ra parts <<< "$names"
for n in "${parts[@]}"; do
  if [[ $n =~ ^[0-9.]+$ || $n == *:* ]]; then san+="IP:$n,"; else san+="DNS:$n,"; fi
done
san=${san%,}

key ca.key
openssl req -x509 -new -key ca.key -sha256 -days "$days" -subj "/CN=twind CA" \
  -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
  -out ca.pem

sign() {  # sign CN EXTFILE
  key "$1.key"
  openssl req -new -key "$1.key" -subj "/CN=$1" -out "$1.csr"
  openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -sha256 \
    -days "$days" -extfile "$2" -out "$1.pem" 2>/dev/null
  rm -f "$1.csr"
}

printf 'basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\nsubjectAltName=%s\n' "$san" > server.ext
sign twin server.ext
printf 'basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\nextendedKeyUsage=clientAuth\n' > client.ext
for cn in "${cns[@]}"; do sign "$cn" client.ext; done
rm -f server.ext client.ext ca.srl
chmod 644 ./*.pem
echo "made ca.pem, twin.pem (${names}) and ${cns[*]} in $out"
