#!/usr/bin/env bash
# Private servers for the tests, on loopback, in one throwaway folder:
#   - PostgreSQL (Debian's postgresql package): a fresh cluster made with initdb, password auth;
#   - an S3-compatible object store: moto's standalone server (moto[server], a real HTTP S3 API;
#     see docs/deploy.md for why not MinIO).
#
#   eval "$(scripts/test-services.sh start DIR)"   # starts both; prints the export lines the tests read:
#       CROWDBAKE_TEST_DATABASE_URL, CROWDBAKE_TEST_S3_URL, CROWDBAKE_TEST_S3_ACCESS_KEY_ID,
#       CROWDBAKE_TEST_S3_SECRET_ACCESS_KEY, CROWDBAKE_TEST_S3_BUCKET
#   scripts/test-services.sh stop DIR              # stops both and deletes DIR (safe after a failed start)
#
# initdb and postgres refuse to run as root; as root the cluster belongs to `nobody` (runuser).
# CROWDBAKE_TEST_SERVICES=s3 or =postgres starts only that one.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
python="${CROWDBAKE_PYTHON:-$root/.venv/bin/python}"
[ -x "$python" ] || python=python3

die() { printf 'test-services: %s\n' "$*" >&2; exit 1; }

free_port() { "$python" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }

wait_for_port() {  # port seconds: until something accepts connections on 127.0.0.1:port
  "$python" - "$1" "$2" <<'EOF'
import socket, sys, time
port, deadline = int(sys.argv[1]), time.monotonic() + float(sys.argv[2])
while time.monotonic() < deadline:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
        sys.exit(0)
    except OSError:
        time.sleep(0.1)
sys.exit(1)
EOF
}

pg_bin() {  # the newest installed server's bin folder (Debian keeps initdb off the PATH)
  local dir
  dir="$(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -n 1)"
  if [ -n "$dir" ]; then echo "$dir"; elif command -v initdb >/dev/null; then dirname "$(command -v initdb)"; else
    die "PostgreSQL is not installed (apt-get install postgresql; scripts/apt-packages.txt lists it)"; fi
}

as_owner() {  # run a PostgreSQL program as the cluster's owner
  if [ "$(id -u)" -eq 0 ]; then runuser -u nobody -- "$@"; else "$@"; fi
}

start_postgres() {
  local dir="$1" bin port password
  bin="$(pg_bin)"
  port="$(free_port)"
  password="$("$python" -c 'import secrets; print(secrets.token_hex(16))')"
  mkdir -p "$dir/pg"
  printf '%s\n' "$password" > "$dir/pg/password"
  [ "$(id -u)" -eq 0 ] && chown -R nobody "$dir/pg"
  as_owner "$bin/initdb" -D "$dir/pg/data" -U crowdbake --pwfile="$dir/pg/password" --auth=scram-sha-256 -E UTF8 --no-sync \
    > "$dir/pg/initdb.log" 2>&1 || { cat "$dir/pg/initdb.log" >&2; die "initdb failed"; }
  # Durability off: the cluster lives for one test run. The socket stays in the folder, not /run.
  # max_connections: the API tests build an app, and so a connection pool, per test in one process.
  as_owner "$bin/pg_ctl" -D "$dir/pg/data" -l "$dir/pg/server.log" -w -t 60 start \
    -o "-c listen_addresses=127.0.0.1 -p $port -k $dir/pg -c max_connections=1000 -c fsync=off -c synchronous_commit=off -c full_page_writes=off" \
    > /dev/null || { cat "$dir/pg/server.log" >&2; die "PostgreSQL did not start"; }
  echo "export CROWDBAKE_TEST_DATABASE_URL='postgresql+psycopg://crowdbake:${password}@127.0.0.1:${port}/postgres'"
}

start_s3() {
  local dir="$1" port
  port="$(free_port)"
  mkdir -p "$dir/s3"
  local server
  server="$(dirname "$python")/moto_server"
  [ -x "$server" ] || server="$(command -v moto_server)" || die "moto_server not found (pip install 'moto[server]'; services/requirements-test.txt pins it)"
  (cd "$dir/s3" && exec "$server" -H 127.0.0.1 -p "$port" > "$dir/s3/server.log" 2>&1) &
  echo $! > "$dir/s3/server.pid"
  wait_for_port "$port" 60 || { cat "$dir/s3/server.log" >&2; die "the S3 server did not start"; }
  echo "export CROWDBAKE_TEST_S3_URL='http://127.0.0.1:${port}'"
  # moto accepts any key pair; real stores (MinIO) need theirs, so the tests always send one.
  echo "export CROWDBAKE_TEST_S3_ACCESS_KEY_ID='crowdbake-test' CROWDBAKE_TEST_S3_SECRET_ACCESS_KEY='crowdbake-test-secret'"
  echo "export CROWDBAKE_TEST_S3_BUCKET='crowdbake-test'"
}

stop_all() {
  local dir="$1"
  [ -n "$dir" ] && [ -d "$dir" ] || return 0
  if [ -f "$dir/pg/data/postmaster.pid" ]; then
    as_owner "$(pg_bin)/pg_ctl" -D "$dir/pg/data" -m immediate -w stop > /dev/null 2>&1 || true
  fi
  if [ -f "$dir/s3/server.pid" ]; then
    local pid
    pid="$(cat "$dir/s3/server.pid")"
    kill "$pid" 2>/dev/null || true
    for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
  fi
  rm -rf "$dir"
}

command="${1:-}"
dir="${2:-}"
[ -n "$dir" ] || die "usage: $0 start|stop DIR"
case "$command" in
  start)
    mkdir -p "$dir"
    [ "$(id -u)" -eq 0 ] && chmod 755 "$dir"  # nobody must reach its cluster folder inside
    wanted="${CROWDBAKE_TEST_SERVICES:-postgres,s3}"
    case ",$wanted," in *,postgres,*) start_postgres "$dir" ;; esac
    case ",$wanted," in *,s3,*) start_s3 "$dir" ;; esac
    ;;
  stop) stop_all "$dir" ;;
  *) die "usage: $0 start|stop DIR" ;;
esac
