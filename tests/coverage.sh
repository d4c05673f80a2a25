#!/usr/bin/env bash
# Test coverage of the native tests (the test command's `cargo test --workspace`, browser end-to-end, AV1 and
# LeRobot fixture tests included), measured by cargo-llvm-cov: a second, instrumented build of the workspace
# (about 40 minutes cold on 2 cores, so the test command does not run it). Prints the per-file table and the
# workspace's total, and fails when the share of lines covered falls under the floor below (the figure the
# README states, rounded down).
#   bash tests/coverage.sh
set -euo pipefail
cd "$(dirname "$0")/.."
source tests/native-env.sh

floor_lines=90
rustup component list --installed | grep -q '^llvm-tools' || rustup component add llvm-tools-preview
llvm_cov_version=0.9.1
if [[ "$(cargo llvm-cov --version 2>/dev/null)" != "cargo-llvm-cov $llvm_cov_version" ]]; then
  cargo install --root "$cache/tools" --force --locked cargo-llvm-cov --version "$llvm_cov_version"
fi
# The www/pkg the browser tests serve (an uninstrumented wasm build, as in the test command).
bash client-wasm/build.sh
# Test files themselves are not counted, only the code they exercise.
cargo llvm-cov --workspace --locked --features fedvla-server/av1 --summary-only \
  --ignore-filename-regex '(/tests/|/benches/|/examples/)' --fail-under-lines "$floor_lines"
