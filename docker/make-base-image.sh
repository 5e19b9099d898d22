#!/bin/sh
# A local stand-in for docker.io/library/python:3.11-slim, made from Debian packages only, for
# hosts that reach a Debian mirror but no container registry (docs/deploy.md, "No registry").
#
#   sudo docker/make-base-image.sh [podman|docker] [IMAGE]
#   sudo ARCH=arm64 docker/make-base-image.sh podman localhost/python:3.11-slim-arm64
#
# Debian bookworm's minbase with its python3.11, set up as a virtualenv at /usr/local so that
# /usr/local/bin/python and /usr/local/bin/pip exist where the official image has them. Needs
# root and debootstrap (apt-get install debootstrap); MIRROR overrides the Debian mirror.
# ARCH (a Debian architecture: arm64, armhf) makes a foreign base: debootstrap then runs the
# foreign binaries through qemu-user-static's binfmt handlers (docs/deploy.md, "arm64").
set -eu

ENGINE=${1:-podman}
IMAGE=${2:-docker.io/library/python:3.11-slim}
MIRROR=${MIRROR:-http://deb.debian.org/debian}
ARCH=${ARCH:-}
ROOTFS=$(mktemp -d /tmp/python-slim-rootfs.XXXXXX)
trap 'rm -rf "$ROOTFS"' EXIT

debootstrap ${ARCH:+--arch "$ARCH"} --variant=minbase bookworm "$ROOTFS" "$MIRROR"
# Python's maintainer scripts want /proc; install it after the base system is configured.
mount -t proc proc "$ROOTFS/proc"
trap 'umount "$ROOTFS/proc" 2>/dev/null || true; rm -rf "$ROOTFS"' EXIT
chroot "$ROOTFS" apt-get install -y --no-install-recommends python3.11 python3.11-venv ca-certificates
umount "$ROOTFS/proc"
chroot "$ROOTFS" /usr/bin/python3.11 -m venv /usr/local
chroot "$ROOTFS" /usr/local/bin/python -c "import ssl, sqlite3, venv"
# What the official image leaves out too: package lists, docs, caches.
rm -rf "$ROOTFS"/var/lib/apt/lists/* "$ROOTFS"/var/cache/apt/*.bin "$ROOTFS"/usr/share/doc/* \
    "$ROOTFS"/usr/share/man/* "$ROOTFS"/usr/share/locale/*

# podman records a foreign image's architecture (docker's import has no such option).
tar -C "$ROOTFS" -c . | "$ENGINE" import ${ARCH:+--arch "$ARCH"} \
    --change 'ENV PATH=/usr/local/bin:/usr/local/sbin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV LANG=C.UTF-8' \
    --change 'CMD ["python3"]' \
    - "$IMAGE"
echo "made $IMAGE"
