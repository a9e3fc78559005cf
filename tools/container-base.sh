#!/usr/bin/env bash
# Makes the two base images the Dockerfile names, locally, when no image
# registry is reachable (CI, air-gapped machines):
#
#   docker.io/library/debian:bookworm-slim       the runtime stage
#   docker.io/library/rust:<RUST_VERSION>-slim-bookworm   the builder stage
#
# Both start from a `debootstrap --variant=minbase` root filesystem. The
# builder adds what the official rust:slim image has (gcc, libc6-dev,
# ca-certificates) and this machine's own Rust toolchain, copied to
# /usr/local/rustup with cargo's and rustc's binaries on PATH, as the
# official image lays them out. An image that already exists is kept, so
# the script is cheap to run again; pass --force to remake both.
#
# Needs root, podman, runc and debootstrap (Debian: apt-get install podman
# runc debootstrap). Where a registry is reachable none of this is needed:
# `podman build` pulls the real images.
set -euo pipefail
cd "$(dirname "$0")/.."
source tools/podman.sh

RUST_VERSION=${RUST_VERSION:-$(sed -n 's/^ARG RUST_VERSION=//p' Dockerfile)}
DEBIAN_RELEASE=${DEBIAN_RELEASE:-$(sed -n 's/^ARG DEBIAN_RELEASE=//p' Dockerfile)}
MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
DEBIAN_IMAGE=docker.io/library/debian:${DEBIAN_RELEASE}-slim
RUST_IMAGE=docker.io/library/rust:${RUST_VERSION}-slim-${DEBIAN_RELEASE}
FORCE=0
[ "${1:-}" = "--force" ] && FORCE=1

have() { [ "$FORCE" -eq 0 ] && podman_ image exists "$1"; }

if have "$DEBIAN_IMAGE" && have "$RUST_IMAGE"; then
  echo "base images present: $DEBIAN_IMAGE, $RUST_IMAGE"
  exit 0
fi

work=$(mktemp -d /var/tmp/mcapi-base.XXXXXX)
trap 'umount -l "$work/rootfs/proc" 2>/dev/null || true; rm -rf "$work"' EXIT
rootfs=$work/rootfs

echo "debootstrap $DEBIAN_RELEASE (minbase) from $MIRROR ..."
start=$(date +%s)
debootstrap --variant=minbase "$DEBIAN_RELEASE" "$rootfs" "$MIRROR" >"$work/debootstrap.log" 2>&1 \
  || { tail -20 "$work/debootstrap.log"; exit 1; }
# What the official slim images drop: documentation, manual pages, locales
# (and dpkg is told to keep dropping them), apt lists and caches.
cat >"$rootfs/etc/dpkg/dpkg.cfg.d/docker-slim" <<'CFG'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/man/*
path-exclude /usr/share/info/*
path-exclude /usr/share/locale/*
path-include /usr/share/locale/locale.alias
path-exclude /usr/share/lintian/*
CFG
find "$rootfs/usr/share/doc" -mindepth 1 -not -name copyright -not -type d -delete
find "$rootfs/usr/share/doc" -mindepth 1 -type d -empty -delete
rm -rf "$rootfs"/usr/share/man/* "$rootfs"/usr/share/info/* "$rootfs"/usr/share/lintian/*
find "$rootfs/usr/share/locale" -mindepth 1 -not -name locale.alias -delete
chroot "$rootfs" apt-get clean
rm -rf "$rootfs"/var/lib/apt/lists/* "$rootfs"/var/cache/apt/*.bin "$rootfs"/var/log/*.log \
  "$rootfs"/var/cache/debconf/*-old "$rootfs"/var/lib/dpkg/*-old
echo "  root filesystem in $(( $(date +%s) - start )) s"

if ! have "$DEBIAN_IMAGE"; then
  tar -C "$rootfs" --numeric-owner -c . \
    | podman_ import --quiet --change 'CMD ["bash"]' - "$DEBIAN_IMAGE" >/dev/null
  echo "  made $DEBIAN_IMAGE"
fi

if ! have "$RUST_IMAGE"; then
  # The real toolchain directory (not rustup's proxies in ~/.cargo/bin).
  toolchain=$(readlink -f "$(rustc --print sysroot)")
  have_version=$("$toolchain/bin/rustc" --version | awk '{print $2}')
  case "$have_version" in
    "$RUST_VERSION"|"$RUST_VERSION".*) ;;
    *) echo "this machine's rustc is $have_version, the Dockerfile wants $RUST_VERSION" >&2; exit 1 ;;
  esac
  cp /etc/resolv.conf "$rootfs/etc/resolv.conf"
  mount -t proc proc "$rootfs/proc"
  chroot "$rootfs" apt-get update -qq
  chroot "$rootfs" env DEBIAN_FRONTEND=noninteractive \
    apt-get install -y -qq --no-install-recommends gcc libc6-dev ca-certificates >/dev/null
  chroot "$rootfs" apt-get clean
  umount "$rootfs/proc"
  rm -rf "$rootfs"/var/lib/apt/lists/* "$rootfs/etc/resolv.conf"
  : >"$rootfs/etc/resolv.conf"
  dest=$rootfs/usr/local/rustup/toolchains/$have_version-x86_64-unknown-linux-gnu
  mkdir -p "$dest" "$rootfs/usr/local/cargo/bin"
  # The compiler, cargo and the standard library; not the HTML docs.
  tar -C "$toolchain" --exclude=./share/doc -c . | tar -C "$dest" -x
  for tool in cargo rustc rustdoc; do
    ln -s "/usr/local/rustup/toolchains/$have_version-x86_64-unknown-linux-gnu/bin/$tool" \
      "$rootfs/usr/local/cargo/bin/$tool"
  done
  tar -C "$rootfs" --numeric-owner -c . \
    | podman_ import --quiet \
        --change 'ENV RUSTUP_HOME=/usr/local/rustup' \
        --change 'ENV CARGO_HOME=/usr/local/cargo' \
        --change 'ENV PATH=/usr/local/cargo/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
        --change "ENV RUST_VERSION=$have_version" \
        --change 'CMD ["bash"]' \
        - "$RUST_IMAGE" >/dev/null
  echo "  made $RUST_IMAGE (rustc $have_version)"
fi
