# Container image of the `mcapi` server.
#
#   docker build -t mcapi .
#   docker run --rm -p 8080:8080 -p 50051:50051 -v mcapi-data:/data mcapi
#
# Linted by `make lint-docker` (tools/hadolint.sh); the Docker engine is not
# needed for that.

# Builder and runtime share one Debian release (bookworm), so the binary links
# against the same glibc it runs on. Keep RUST_VERSION at or above the
# toolchain the project is tested with.
ARG RUST_VERSION=1.95
ARG DEBIAN_RELEASE=bookworm

# ---------------------------------------------------------------------------
# Builder
# ---------------------------------------------------------------------------
FROM rust:${RUST_VERSION}-slim-${DEBIAN_RELEASE} AS builder

# The slim image already has gcc and libc6-dev for linking; protobuf is
# compiled by protox (pure Rust) in build.rs, so no system protoc is needed.
WORKDIR /build

# 1. Dependencies only: the manifest, the lock file, the build script and the
#    .proto files it compiles, with stub targets. This layer is rebuilt only
#    when one of those changes, not on every edit of src/.
#    benches/tick.rs must exist for cargo to accept the manifest's [[bench]].
COPY Cargo.toml Cargo.lock build.rs ./
COPY proto ./proto
RUN mkdir -p src benches \
    && echo 'fn main() {}' > src/main.rs \
    && : > src/lib.rs \
    && echo 'fn main() {}' > benches/tick.rs \
    && cargo build --release --locked \
    && rm -rf src benches \
        target/release/mcapi target/release/mcapi.d \
        target/release/.fingerprint/mcapi-* \
        target/release/deps/mcapi-* target/release/deps/libmcapi-*

# 2. The crate itself. assets/ and data/ are compiled into the binary
#    (include_bytes!/include_str!), benches/ is needed by the manifest.
COPY assets ./assets
COPY data ./data
COPY benches ./benches
COPY src ./src
RUN cargo build --release --locked \
    && install -D -m 0755 target/release/mcapi /out/mcapi

# ---------------------------------------------------------------------------
# Runtime
# ---------------------------------------------------------------------------
FROM debian:${DEBIAN_RELEASE}-slim AS runtime

LABEL org.opencontainers.image.title="mcapi" \
      org.opencontainers.image.description="Hosts motivated reinforcement-learning agents (MCA-PI) as sessions" \
      org.opencontainers.image.licenses="MIT OR Apache-2.0"

# A fixed, unprivileged uid/gid (10001) so volume ownership is predictable.
RUN groupadd --system --gid 10001 mcapi \
    && useradd --system --no-log-init --uid 10001 --gid mcapi \
        --home-dir /data --no-create-home --shell /usr/sbin/nologin mcapi \
    && mkdir -p /data \
    && chown mcapi:mcapi /data

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
