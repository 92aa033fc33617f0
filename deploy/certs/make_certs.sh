#!/usr/bin/env bash
# Make a site CA and the TLS certificates of a RayFronts deployment (Zenoh mutual TLS).
#
#   deploy/certs/make_certs.sh -o OUT [--host NAME]... [--ip ADDR]... \
#       [--robot ID]... [--operator NAME]... [--days N] [--no-acl]
#
# Writes one directory per identity, each holding exactly what that machine needs:
#   OUT/ca/ca.pem, OUT/ca/ca-key.pem    the site CA (keep ca-key.pem offline / off robots)
#   OUT/router/                         CN=router, server+client cert with SANs --host/--ip
#   OUT/mapper/                         CN=mapper, same SANs (the mapper may be the router)
#   OUT/robot-<id>/                     CN=robot-<id>, one per --robot
#   OUT/operator-<name>/                CN=operator-<name>, one per --operator
# each with ca.pem (the site CA), cert.pem, key.pem (mode 600). Copy an identity's
# directory to its machine as /etc/rayfronts/certs (or point RAYFRONTS_CERTS / --certs at
# it): the shipped deploy/zenoh/*-tls.json5 files name ca.pem, cert.pem and key.pem relative
# to that directory. The Zenoh ACL identifies subjects by these common names.
#
# Also writes OUT/acl.json5 (deploy/acl/make_acl.py) for the robots and operators given,
# unless --no-acl or python3 is missing.
#
# Idempotent: an existing CA and existing certificates are kept (delete a directory to
# re-issue it; changing --host/--ip needs the router/ and mapper/ directories deleted).
# Defaults: --host localhost --ip 127.0.0.1, --days 825, EC P-256 keys, SHA-256.
set -euo pipefail

OUT=""
DAYS=825
HOSTS=()
IPS=()
ROBOTS=()
OPERATORS=()
ACL=1
PREFIX=rayfronts
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"

usage() { sed -n '2,24p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'; }

while [ $# -gt 0 ]; do
  case "$1" in
    -o|--out) OUT="$2"; shift 2 ;;
    --host) HOSTS+=("$2"); shift 2 ;;
    --ip) IPS+=("$2"); shift 2 ;;
    --robot) ROBOTS+=("$2"); shift 2 ;;
    --operator) OPERATORS+=("$2"); shift 2 ;;
    --days) DAYS="$2"; shift 2 ;;
    --prefix) PREFIX="$2"; shift 2 ;;
    --no-acl) ACL=0; shift ;;
    -h|--help) usage; exit 0 ;;
    *) echo "make_certs.sh: unknown argument: $1 (see --help)" >&2; exit 2 ;;
  esac
done
[ -n "$OUT" ] || { echo "make_certs.sh: -o OUT is required (see --help)" >&2; exit 2; }
command -v openssl >/dev/null || { echo "make_certs.sh: openssl not found (apt-get install openssl)" >&2; exit 2; }
[ ${#HOSTS[@]} -gt 0 ] || HOSTS=(localhost)
[ ${#IPS[@]} -gt 0 ] || IPS=(127.0.0.1)
valid_id() { [[ "$1" =~ ^[A-Za-z0-9_-]{1,64}$ ]]; }
for r in "${ROBOTS[@]}" "${OPERATORS[@]}"; do
  valid_id "$r" || { echo "make_certs.sh: invalid id '$r' (use [A-Za-z0-9_-], 1-64 chars)" >&2; exit 2; }
done

mkdir -p "$OUT"
OUT="$(cd "$OUT" && pwd)"
umask 077
TMP="$(mktemp -d)"
trap 'rm -rf "$TMP"' EXIT

# new_key FILE: a new EC P-256 private key in FILE (PEM)
new_key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

# req_config CN [REQ_LINE]: the head of an openssl req config on stdout: the [req] section
# (plus REQ_LINE) and the subject CN=CN, O=RayFronts; the caller appends extension sections
req_config() {
  printf '%s\n' "[req]" "distinguished_name = dn" "prompt = no" ${2:+"$2"} "[dn]" "CN = $1" "O = RayFronts"
}

# ----------------------------------------------------------------------------- CA
CA_DIR="$OUT/ca"
if [ ! -s "$CA_DIR/ca.pem" ] || [ ! -s "$CA_DIR/ca-key.pem" ]; then
  mkdir -p "$CA_DIR"
  new_key "$CA_DIR/ca-key.pem"
  { req_config "RayFronts site CA" "x509_extensions = v3_ca"; cat <<EOF; } > "$TMP/ca.cnf"
[v3_ca]
basicConstraints = critical, CA:TRUE, pathlen:0
keyUsage = critical, keyCertSign, cRLSign
subjectKeyIdentifier = hash
EOF
  openssl req -x509 -new -key "$CA_DIR/ca-key.pem" -sha256 -days "$((DAYS * 2))" \
    -config "$TMP/ca.cnf" -out "$CA_DIR/ca.pem"
  chmod 644 "$CA_DIR/ca.pem"
  echo "[certs] new CA: $CA_DIR/ca.pem"
else
  echo "[certs] keeping CA: $CA_DIR/ca.pem"
fi

# ----------------------------------------------------------------------------- leaf certs
# issue NAME SAN   (SAN is an openssl subjectAltName value)
issue() {
  local name="$1" san="$2" dir="$OUT/$1"
  if [ -s "$dir/cert.pem" ] && [ -s "$dir/key.pem" ] && [ -s "$dir/ca.pem" ] \
     && openssl verify -CAfile "$CA_DIR/ca.pem" "$dir/cert.pem" >/dev/null 2>&1; then
    echo "[certs] keeping $name"
    return
  fi
  mkdir -p "$dir"
  new_key "$dir/key.pem"
  { req_config "$name"; cat <<EOF; } > "$TMP/$name.cnf"
[v3_leaf]
basicConstraints = critical, CA:FALSE
keyUsage = critical, digitalSignature, keyEncipherment
extendedKeyUsage = serverAuth, clientAuth
subjectAltName = $san
subjectKeyIdentifier = hash
authorityKeyIdentifier = keyid
EOF
  openssl req -new -key "$dir/key.pem" -config "$TMP/$name.cnf" -out "$TMP/$name.csr"
  openssl x509 -req -in "$TMP/$name.csr" -CA "$CA_DIR/ca.pem" -CAkey "$CA_DIR/ca-key.pem" \
    -CAcreateserial -CAserial "$CA_DIR/ca.srl" -days "$DAYS" -sha256 \
    -extfile "$TMP/$name.cnf" -extensions v3_leaf -out "$dir/cert.pem" 2>/dev/null
  cp "$CA_DIR/ca.pem" "$dir/ca.pem"
  chmod 600 "$dir/key.pem"
  chmod 644 "$dir/cert.pem" "$dir/ca.pem"
  echo "[certs] issued $name ($san)"
}

SERVER_SAN=""
for h in "${HOSTS[@]}"; do SERVER_SAN+="${SERVER_SAN:+,}DNS:$h"; done
for i in "${IPS[@]}"; do SERVER_SAN+="${SERVER_SAN:+,}IP:$i"; done

issue router "$SERVER_SAN"
issue mapper "$SERVER_SAN"
for r in "${ROBOTS[@]}"; do issue "robot-$r" "DNS:robot-$r"; done
for o in "${OPERATORS[@]}"; do issue "operator-$o" "DNS:operator-$o"; done

# ----------------------------------------------------------------------------- ACL
if [ "$ACL" = 1 ]; then
  PY="${PYTHON:-python3}"
  if command -v "$PY" >/dev/null; then
    args=(--prefix "$PREFIX" -o "$OUT/acl.json5")
    for r in "${ROBOTS[@]}"; do args+=(--robot "$r"); done
    for o in "${OPERATORS[@]}"; do args+=(--operator "$o"); done
    "$PY" "$HERE/../acl/make_acl.py" "${args[@]}"
    chmod 644 "$OUT/acl.json5"
  else
    echo "[certs] $PY not found: skipped acl.json5 (run deploy/acl/make_acl.py yourself)"
  fi
fi
echo "[certs] done: $OUT"
