#!/usr/bin/env bash
# The project's test command (README "Run the tests"): the browser volunteer built for wasm32 and its units run
# in headless Chromium, then every crate's tests natively, the browser end-to-end tests included (they need
# Debian's chromium and chromium-driver and the wasm-bindgen CLI of Cargo.lock's version; AV1 decoding needs
# libdav1d-dev and its test ffmpeg: .ci/run installs them all).
set -euo pipefail
cd "$(dirname "$0")/.."

# One style (rustfmt.toml), checked first because it is instant.
cargo fmt --check
# The wasm volunteer into www/pkg, which the server serves and the browser tests load.
bash client-wasm/build.sh
# The wasm units (codec, sim, SmolVLA training on the CPU backend and on WebGPU) in a real Chromium.
CHROMEDRIVER="${CHROMEDRIVER:-/usr/bin/chromedriver}" WASM_BINDGEN_TEST_TIMEOUT=600 \
  wasm-pack test --release --headless --chrome client-wasm
# Everything native, AV1 decoding included; a missing browser or ffmpeg (to encode the AV1 test clip) is a
# failure here, not a skip.
FEDVLA_REQUIRE_BROWSER=1 FEDVLA_REQUIRE_AV1=1 cargo test --workspace --locked --features fedvla-server/av1
