#!/bin/sh
# A private CA and one certificate per party of the secured deployment (deploy/secure/), with openssl.
#
#   deploy/secure/make-certs.sh [OUT_DIR] [ROBOT ...]     # default: deploy/secure/certs robot1
#
# Writes into OUT_DIR (created mode 0700; nothing here is committed, see .gitignore):
#   ca.pem                      the CA every party trusts (root_ca_certificate)
#   ca.key                      the CA's key: signs the others; keep it off the machines that run objslam
#   router.pem, router.key      the zenoh router (server certificate, names zenoh-router, localhost, 127.0.0.1)
#   service.pem, service.key    the objslam service           (client certificate, common name "objslam-service")
#   ROBOT.pem, ROBOT.key        each robot's replay / driver   (common name "ROBOT", e.g. "robot1")
#   operator.pem, operator.key  an operator's `objslam status` / `objslam save` (common name "operator")
# The router's access control (router.json5) knows the parties by these common names.
# An existing CA in OUT_DIR is reused (the other certificates are issued anew), so a robot can be added later:
#   make-certs.sh deploy/secure/certs robot1 robot2
# Keys are mode 0644 inside the 0700 directory: the compose file bind-mounts each file on its own into a
# container whose user is not the host user; the directory keeps them from other users of the host.
set -eu

here=$(cd "$(dirname "$0")" && pwd)
out=${1:-"$here/certs"}
if [ "$#" -gt 0 ]; then shift; fi
robots=${*:-robot1}
days=${CERT_DAYS:-365}

for robot in $robots; do
    case $robot in
    ca | router | service | operator | *[!A-Za-z0-9_-]*)
        echo "make-certs.sh: '$robot' cannot name a robot (a zenoh key chunk other than ca, router, service, operator)" >&2
        exit 2
        ;;
    esac
done

umask 077
mkdir -p "$out"
chmod 0700 "$out"
cd "$out"

new_key() {  # ECDSA P-256, PKCS#8
    openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1.key" 2>/dev/null
}

if [ ! -f ca.pem ] || [ ! -f ca.key ]; then
    new_key ca
    openssl req -x509 -new -key ca.key -sha256 -days "$days" -subj "/CN=objslam-ca" \
        -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
        -out ca.pem
fi

# issue NAME COMMON_NAME EXTENDED_KEY_USAGE [SUBJECT_ALT_NAMES]
issue() {
    new_key "$1"
    openssl req -new -key "$1.key" -subj "/CN=$2" -out "$1.csr"
    {
        echo "basicConstraints=critical,CA:FALSE"
        echo "keyUsage=critical,digitalSignature"
        echo "extendedKeyUsage=$3"
        if [ -n "${4:-}" ]; then echo "subjectAltName=$4"; fi
    } >"$1.ext"
    openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -sha256 -days "$days" \
        -extfile "$1.ext" -out "$1.pem" 2>/dev/null
    rm -f "$1.csr" "$1.ext"
    chmod 0644 "$1.key" "$1.pem"
}

issue router zenoh-router serverAuth "DNS:zenoh-router,DNS:localhost,IP:127.0.0.1"
issue service objslam-service clientAuth
issue operator operator clientAuth
for robot in $robots; do
    issue "$robot" "$robot" clientAuth
done
chmod 0644 ca.pem
rm -f ca.srl

echo "certificates for router, service, operator and $robots in $out"
