# horizon-bake service image: build in the official Rust image, run as a non-root user on a
# slim Debian with the data directory on a volume.
FROM rust:1.95-bookworm AS build
WORKDIR /src
COPY Cargo.toml Cargo.lock ./
COPY src ./src
COPY benches ./benches
COPY openapi.yaml README.md ./
RUN cargo build --release --locked --bin horizon-bake \
    && strip target/release/horizon-bake

FROM debian:bookworm-slim
RUN useradd --system --uid 10001 --user-group --home-dir /data --shell /usr/sbin/nologin horizon \
    && mkdir -p /data \
    && chown horizon:horizon /data
COPY --from=build /src/target/release/horizon-bake /usr/local/bin/horizon-bake
USER 10001:10001
WORKDIR /data
VOLUME ["/data"]
ENV HORIZON_ADDR=0.0.0.0:8080 \
    HORIZON_DATA_DIR=/data
EXPOSE 8080
# No curl in the slim image: bash's /dev/tcp speaks enough HTTP for /healthz.
HEALTHCHECK --interval=30s --timeout=3s --start-period=10s --retries=3 \
    CMD ["bash", "-c", "exec 3<>/dev/tcp/127.0.0.1/8080 && printf 'GET /healthz HTTP/1.0\\r\\n\\r\\n' >&3 && grep -q ' 200 ' <&3"]
STOPSIGNAL SIGTERM
ENTRYPOINT ["horizon-bake"]
CMD ["serve"]
