#!/usr/bin/env bash
# Make a project CA and scheduler / worker / client certificates for Dask mutual TLS.
#
#   deploy/tls/make-certs.sh OUT_DIR [HOST ...]
#
# HOSTs (default: 127.0.0.1 localhost) become subject alternative names (IP or DNS) of
# every certificate. Writes, in OUT_DIR:
#   ca.pem ca-key.pem                        project CA (keep ca-key.pem off the cluster)
#   scheduler.pem scheduler-key.pem          scheduler
#   worker.pem worker-key.pem                workers
#   client.pem client-key.pem                whoever submits work (schlieren run/submit)
# Same layout as `schlieren tls init OUT_DIR` (the Python equivalent, no openssl needed).
# Keys are ECDSA P-256, mode 0600; certificates are valid DAYS days (default 365).
set -euo pipefail

if [[ $# -lt 1 || "$1" == "-h" || "$1" == "--help" ]]; then
    sed -n '2,14p' "$0" | sed 's/^# \{0,1\}//'
    exit 2
fi
command -v openssl >/dev/null || { echo "make-certs.sh: openssl not found (use: schlieren tls init DIR)" >&2; exit 1; }

out=$1; shift
hosts=("$@")
[[ ${#hosts[@]} -gt 0 ]] || hosts=(127.0.0.1 localhost)
days=${DAYS:-365}

if [[ -e "$out/ca.pem" && -z "${OVERWRITE:-}" ]]; then
    echo "make-certs.sh: $out/ca.pem exists; set OVERWRITE=1 to replace the CA" >&2
    exit 1
fi
mkdir -p "$out"
umask 077
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

san=""
for h in "${hosts[@]}"; do
    if [[ $h =~ ^[0-9.]+$ || $h == *:* ]]; then san+="IP:$h,"; else san+="DNS:$h,"; fi
done
san=${san%,}

cat >"$tmp/ca.cnf" <<EOF
[req]
distinguished_name = dn
prompt = no
x509_extensions = v3_ca
[dn]
CN = schlieren project CA
[v3_ca]
basicConstraints = critical, CA:TRUE, pathlen:0
keyUsage = critical, keyCertSign, cRLSign, digitalSignature
subjectKeyIdentifier = hash
EOF

cat >"$tmp/leaf.cnf" <<EOF
[v3_leaf]
basicConstraints = critical, CA:FALSE
keyUsage = critical, digitalSignature, keyAgreement
extendedKeyUsage = serverAuth, clientAuth
subjectAltName = $san
subjectKeyIdentifier = hash
authorityKeyIdentifier = keyid
EOF

openssl ecparam -name prime256v1 -genkey -noout -out "$tmp/ca.key"
openssl pkcs8 -topk8 -nocrypt -in "$tmp/ca.key" -out "$out/ca-key.pem"
openssl req -x509 -new -key "$out/ca-key.pem" -sha256 -days "$days" \
    -config "$tmp/ca.cnf" -out "$out/ca.pem"

for role in scheduler worker client; do
    openssl ecparam -name prime256v1 -genkey -noout -out "$tmp/$role.key"
    openssl pkcs8 -topk8 -nocrypt -in "$tmp/$role.key" -out "$out/$role-key.pem"
    openssl req -new -key "$out/$role-key.pem" -subj "/CN=schlieren-$role" -out "$tmp/$role.csr"
    openssl x509 -req -in "$tmp/$role.csr" -CA "$out/ca.pem" -CAkey "$out/ca-key.pem" \
        -CAcreateserial -CAserial "$tmp/ca.srl" -sha256 -days "$days" \
        -extfile "$tmp/leaf.cnf" -extensions v3_leaf -out "$out/$role.pem" 2>/dev/null
    openssl verify -CAfile "$out/ca.pem" "$out/$role.pem" >/dev/null
done
chmod 600 "$out"/*-key.pem
chmod 644 "$out"/ca.pem "$out"/scheduler.pem "$out"/worker.pem "$out"/client.pem
echo "wrote CA and scheduler/worker/client certificates for ${hosts[*]} to $out"
