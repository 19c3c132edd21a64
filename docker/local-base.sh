#!/bin/sh
# Build a local stand-in for the official python:3.11-slim-bookworm image, for machines that
# reach Debian's package mirror but no container registry: mmdebstrap assembles a Debian
# bookworm root file system (python3 3.11, venv, CA certificates) and `podman import` turns it
# into an image. Skipped when the tag exists (delete it with `podman rmi TAG` to rebuild).
#
#   docker/local-base.sh [TAG]          (default localhost/hmpf-base:bookworm-py311; root)
#
# The result is used as the Dockerfile's base: --build-arg PYTHON_IMAGE=TAG.
# Environment: DEBIAN_MIRROR (default http://deb.debian.org/debian), PODMAN (default podman).
set -eu

TAG=${1:-localhost/hmpf-base:bookworm-py311}
PODMAN=${PODMAN:-podman}
MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}

if $PODMAN image exists "$TAG"; then
    echo "base image $TAG exists (podman rmi $TAG to rebuild)"
    exit 0
fi

# As in Debian's official images: apt keeps no package cache and no downloaded .deb files
# (an `apt-get install` in a Dockerfile leaves no 80 MB of /var/cache/apt in its layer).
export APT_CLEAN='DPkg::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
APT::Update::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
Dir::Cache::pkgcache "";
Dir::Cache::srcpkgcache "";'
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT INT TERM
# minbase: the Essential packages and apt. passwd: useradd (the runtime stage's user);
# python-is-python3: `python` as in the official image; python3-venv: venv with pip.
mmdebstrap --variant=minbase --quiet \
    --include=ca-certificates,passwd,python3,python3-venv,python-is-python3 \
    --customize-hook='rm -rf "$1"/var/cache/apt/* "$1"/usr/share/doc/* "$1"/usr/share/man/*' \
    --customize-hook='printf "%s\n" "$APT_CLEAN" >"$1"/etc/apt/apt.conf.d/docker-clean' \
    bookworm "$tmp/rootfs.tar" "deb $MIRROR bookworm main" \
    "deb $MIRROR bookworm-updates main" \
    "deb ${MIRROR%/debian}/debian-security bookworm-security main"
$PODMAN import --quiet \
    --change 'ENV=LANG=C.UTF-8' \
    --change 'ENV=PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'CMD=["python3"]' \
    --message "hmpf local base: Debian bookworm (mmdebstrap), python3 3.11" \
    "$tmp/rootfs.tar" "$TAG" >/dev/null
echo "base image $TAG built: $($PODMAN image inspect --format '{{.Size}}' "$TAG") bytes"
