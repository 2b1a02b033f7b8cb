#!/usr/bin/env bash
# Runs every check CI runs: formatting, lints, the layering rule, and all tests.
# This is the README's test command; .ci/run calls exactly this after setup.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

step() { echo; echo "==> $*"; }

# Mesa's software Vulkan wants a private runtime directory; give it one if the session has none.
if [ -z "${XDG_RUNTIME_DIR:-}" ] || [ ! -d "$XDG_RUNTIME_DIR" ]; then
  export XDG_RUNTIME_DIR="${TMPDIR:-/tmp}/rover-twin-xdg-$(id -u)"
  mkdir -p "$XDG_RUNTIME_DIR" && chmod 700 "$XDG_RUNTIME_DIR"
fi

step "cargo fmt --check"
cargo fmt --all -- --check

step "layering"
scripts/check_layering.sh

step "cargo clippy --all-targets -D warnings"
cargo clippy --workspace --all-targets --locked -- -D warnings

step "cargo test"
cargo test --workspace --locked

step "logs read by the official readers (python mcap, rerun-sdk), Foxglove messages checked against Foxglove's schemas"
logs="$(mktemp -d)"
trap 'rm -rf "$logs"' EXIT
cargo run --locked -q -p scenarios --bin rover-twin -- run tests/e2e/data/short.toml --out "$logs" --quiet
scripts/validate_logs.sh "$logs"
# With the rendered cameras: images, point clouds and their annotations too.
cargo run --locked -q -p scenarios --bin rover-twin -- run tests/e2e/data/cameras.toml --out "$logs/cameras" --quiet >/dev/null
scripts/validate_logs.sh "$logs/cameras"

step "a sweep's junit.xml validated against the JUnit schema"
cargo run --locked -q -p scenarios --bin rover-twin -- sweep tests/e2e/data/junit_sweep.toml --out "$logs/sweep" --quiet >/dev/null
scripts/validate_junit.sh "$logs/sweep/junit.xml"

echo; echo "all checks passed"
