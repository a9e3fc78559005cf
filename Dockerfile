# Container image of the `mcapi` server.
#
#   docker build -t mcapi .
#   docker run --rm -p 8080:8080 -p 50051:50051 -v mcapi-data:/data mcapi
#
# `make container-test` (tools/container-test.sh) builds this file with
# podman and runs the image: REST and gRPC sessions, SIGTERM and SIGKILL
# with a restart on the same volume, the health check, a read-only root
# filesystem. `make lint-docker` runs hadolint on it.
#
# Reproducible builds: pass the commit time, version and revision, e.g.
#   docker build --build-arg SOURCE_DATE_EPOCH=$(git log -1 --format=%ct) \
#                --build-arg VERSION=0.1.0 --build-arg REVISION=$(git rev-parse HEAD) -t mcapi .
# BuildKit (0.11+) takes the image's creation time from SOURCE_DATE_EPOCH
# (and the files' times too with `--output type=image,rewrite-timestamp=true`);
# podman/buildah do both with `--timestamp "$SOURCE_DATE_EPOCH"`.

# Builder and runtime share one Debian release (bookworm), so the binary links
# against the same glibc it runs on. Keep RUST_VERSION at or above the
# toolchain the project is tested with (rust-toolchain or CI).
ARG RUST_VERSION=1.95
ARG DEBIAN_RELEASE=bookworm
ARG CARGO_CHEF_VERSION=0.1.78

# ---------------------------------------------------------------------------
# Dependency caching with cargo-chef: `prepare` reads every manifest of the
# workspace into recipe.json, `cook` builds the dependencies from it alone.
# The cooked layer is rebuilt only when a manifest or Cargo.lock changes,
# and no list of targets is written here to drift from Cargo.toml.
# ---------------------------------------------------------------------------
FROM rust:${RUST_VERSION}-slim-${DEBIAN_RELEASE} AS chef
ARG CARGO_CHEF_VERSION
RUN cargo install --locked --quiet cargo-chef --version "${CARGO_CHEF_VERSION}" \
    && rm -rf "${CARGO_HOME}/registry"
WORKDIR /build

FROM chef AS planner
COPY . .
RUN cargo chef prepare --recipe-path recipe.json

FROM chef AS builder
# protobuf is compiled by protox (pure Rust) in a build script, so no system
# protoc is needed; the slim image's gcc and libc6-dev do the linking.
COPY --from=planner /build/recipe.json recipe.json
RUN cargo chef cook --release --locked --recipe-path recipe.json --bin mcapi
COPY . .
# The release profile keeps line tables for profiling on a host (48 of the
# binary's 68 MB); the image drops them and keeps the symbols, so a
# backtrace still names every function.
RUN cargo build --release --locked --bin mcapi \
    && install -D -m 0755 target/release/mcapi /out/mcapi \
    && strip --strip-debug /out/mcapi \
    && /out/mcapi --version

# ---------------------------------------------------------------------------
# Runtime: Debian slim, the binary and an unprivileged user. No compiler,
# no package cache, no curl (the binary is its own health probe).
# ---------------------------------------------------------------------------
FROM debian:${DEBIAN_RELEASE}-slim AS runtime

# A fixed, unprivileged uid/gid (10001) so volume ownership is predictable.
RUN groupadd --system --gid 10001 mcapi \
    && useradd --system --no-log-init --uid 10001 --gid mcapi \
        --home-dir /data --no-create-home --shell /usr/sbin/nologin mcapi \
    && mkdir -p /data \
    && chown mcapi:mcapi /data \
    && rm -rf /var/log/apt /var/log/dpkg.log /var/cache/debconf/*-old /var/lib/dpkg/*-old

COPY --from=builder /out/mcapi /usr/local/bin/mcapi

# Inside a container the server listens on all interfaces and logs JSON.
ENV MCAPI_STORE=redb \
    MCAPI_DATA_DIR=/data \
    MCAPI_HTTP=0.0.0.0:8080 \
    MCAPI_GRPC=0.0.0.0:50051 \
    MCAPI_LOG_FORMAT=json

WORKDIR /data
VOLUME ["/data"]
# Numeric, so Kubernetes' runAsNonRoot can verify it without /etc/passwd.
USER 10001:10001

# 8080: HTTP API (including /healthz); 50051: gRPC.
EXPOSE 8080 50051

# The image has no curl: the binary probes its own HTTP endpoint and exits 0
# on a 200. If MCAPI_HTTP is moved to another port, override this too.
HEALTHCHECK --interval=30s --timeout=5s --start-period=15s --retries=3 \
    CMD ["mcapi", "healthcheck", "--url", "http://127.0.0.1:8080/healthz"]

# The server runs as PID 1 and must shut down on SIGTERM (docker stop).
STOPSIGNAL SIGTERM
ENTRYPOINT ["mcapi"]
CMD ["serve"]

# Labels last, so a new revision rebuilds only this metadata layer. The
# creation time is the image's own (from SOURCE_DATE_EPOCH, see the top).
ARG VERSION=unknown
ARG REVISION=unknown
LABEL org.opencontainers.image.title="mcapi" \
      org.opencontainers.image.description="Hosts motivated reinforcement-learning agents (MCA-PI) as sessions over REST and gRPC" \
      org.opencontainers.image.licenses="MIT OR Apache-2.0" \
      org.opencontainers.image.version="${VERSION}" \
      org.opencontainers.image.revision="${REVISION}"
