#!/usr/bin/env bash
# Sets everything up (scripts/setup.sh), then runs every test: Python (pytest) and C++ (ctest).
# Starts private servers on loopback and stops them afterwards, also when a test or a start fails:
# redis-server for the integration tests, and PostgreSQL and an S3 server (scripts/test-services.sh)
# so the storage, record and API tests run on PostgreSQL and the store contracts on S3 as well.
# CROWDBAKE_TEST_SERVICES=none skips the last two (=postgres or =s3 starts only that one).
# Tests marked slow (the fault-injection, load and long end-to-end tests) run only with
# CROWDBAKE_SLOW_TESTS=1, which .ci/run sets: CI runs every test, a local run stays short.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
bash scripts/setup.sh

export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-osmesa}"
mkdir -p out/test
redis_dir="$(mktemp -d)"
redis_port="${CROWDBAKE_TEST_REDIS_PORT:-6391}"
redis-server --port "$redis_port" --bind 127.0.0.1 --save "" --appendonly no --dir "$redis_dir" \
  --daemonize yes --pidfile "$redis_dir/redis.pid" --logfile "$redis_dir/redis.log"
services_dir="$(mktemp -d)"
cleanup() {
  if [ -f "$redis_dir/redis.pid" ]; then
    pid="$(cat "$redis_dir/redis.pid")"
    kill "$pid" 2>/dev/null || true
    # Redis still writes its log while it shuts down: removing its folder before it exits can fail.
    for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
  fi
  rm -rf "$redis_dir" || true
  bash scripts/test-services.sh stop "$services_dir" || true
}
trap cleanup EXIT
export CROWDBAKE_TEST_REDIS_URL="redis://127.0.0.1:${redis_port}/0"
if [ "${CROWDBAKE_TEST_SERVICES:-postgres,s3}" != none ]; then
  services_env="$(bash scripts/test-services.sh start "$services_dir")"
  eval "$services_env"
fi

status=0
echo "== Python tests (pytest) =="
markers=(-m "not slow")
[ "${CROWDBAKE_SLOW_TESTS:-0}" = 1 ] && markers=()
.venv/bin/python -m pytest services/tests tests -q -p no:cacheprovider --junitxml=out/test/pytest.xml "${markers[@]}" "$@" || status=$?
echo "== C++ tests (ctest) =="
ctest --test-dir build/runtime --output-on-failure || status=$?
exit "$status"
