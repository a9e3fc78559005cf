# Sourced by the container scripts: `podman_` runs podman with the flags
# that work on CI machines with hybrid cgroups and tight rlimits (crun
# refuses them; runc with the cgroupfs manager does not). Override with
# PODMAN="podman" where the defaults work.
PODMAN=${PODMAN:-podman --runtime runc --cgroup-manager=cgroupfs}
# Every container gets these rlimits (the engine's defaults are refused).
PODMAN_ULIMITS=(--ulimit nofile=4096:4096 --ulimit nproc=4096:4096)
podman_() { $PODMAN "$@"; }
