#!/bin/sh
# The site router's TLS certificate and login (docs/deploy.md, "Several machines: the router"):
#
#   machine credentials init secrets                    # first: the site's logins
#   docker/site-certs.sh secrets ride-1.plant.example 10.0.0.11
#
# makes, in DIR (first argument), the site's CA once (site-ca.crt, site-ca.key) and a router
# certificate signed by it (router.crt, router.key) for `router` (the compose service this
# host's machine dials) and the names and addresses that follow (those other hosts' routers
# dial). Its common name is `router`: the profile's subject `router-certificate`
# (zenoh/acl.json5) is what a machine or router that dials it trusts. Once, too, the routers'
# login `router` (router.password, and its line in DIR/zenoh-users): what one router presents
# where it dials another. Run it once per host with that host's names where site-ca.key is, and
# copy site-ca.crt, router.crt, router.key and router.password to that host (with the site's
# zenoh-users); keep site-ca.key on one host only.
set -eu

if [ $# -lt 1 ]; then
    echo "usage: $0 DIR [NAME-OR-ADDRESS...]" >&2
    exit 2
fi
dir=$1
shift
command -v openssl >/dev/null 2>&1 || { echo "$0: openssl is needed" >&2; exit 2; }
if [ ! -f "$dir/zenoh-users" ]; then
    echo "$0: $dir/zenoh-users is missing: make the site's logins first (machine credentials init $dir)" >&2
    exit 2
fi

umask 077
mkdir -p "$dir"
san="DNS:router"
for name in "$@"; do
    case $name in
        *[!0-9.]*) entry="DNS:$name" ;;
        *) entry="IP:$name" ;;
    esac
    san="${san:+$san,}$entry"
done

if [ ! -f "$dir/site-ca.key" ]; then
    openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$dir/site-ca.key" 2>/dev/null
    openssl req -x509 -new -key "$dir/site-ca.key" -subj "/CN=ride site CA" -days 3650 \
        -addext basicConstraints=critical,CA:TRUE -addext keyUsage=keyCertSign \
        -out "$dir/site-ca.crt"
fi

ext=$(mktemp)
trap 'rm -f "$ext" "$dir/router.csr"' EXIT
printf '%s\n' "basicConstraints=CA:FALSE" "keyUsage=digitalSignature,keyEncipherment" \
    "extendedKeyUsage=serverAuth" "subjectAltName=$san" > "$ext"
openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$dir/router.key" 2>/dev/null
openssl req -new -key "$dir/router.key" -subj "/CN=router" -out "$dir/router.csr"
openssl x509 -req -in "$dir/router.csr" -CA "$dir/site-ca.crt" -CAkey "$dir/site-ca.key" \
    -CAcreateserial -days 825 -extfile "$ext" -out "$dir/router.crt" 2>/dev/null
echo "$dir/router.crt: CN=router, $san (signed by $dir/site-ca.crt)"

# The routers' login: 192 random bits, URL-safe (no ':' for the dictionary), as the machine's.
if [ ! -f "$dir/router.password" ]; then
    if grep -q '^router:' "$dir/zenoh-users"; then
        echo "$0: $dir/zenoh-users has a router login but $dir/router.password is missing" >&2
        exit 2
    fi
    password=$(openssl rand -base64 24 | tr '+/' '-_' | tr -d '=\n')
    printf '%s\n' "$password" > "$dir/router.password"
    printf 'router:%s\n' "$password" >> "$dir/zenoh-users"
    echo "$dir/router.password: the login router (and its line in $dir/zenoh-users: restart the machine)"
fi
