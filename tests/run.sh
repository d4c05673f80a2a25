#!/usr/bin/env bash
# The project's test command (README "Run the tests"), on a fresh machine as on a warm one. It installs what is
# missing (tests/install.sh), checks formatting, builds the browser volunteer for wasm32 and runs its units in
# headless Chromium, makes LeRobot golden fixtures with one to three cameras of non-square sizes (LeRobot 0.6.1
# in the chroot of ../shared/tools/lerobot-check), then runs every crate's tests natively, the browser end-to-end
# tests, AV1 decoding and every fixture comparison included: here a missing browser, ffmpeg or fixture is a
# failure, not a skip. Builds and tools live outside the clone, in $FEDVLA_CACHE (~/.cache/fedvla).
set -euo pipefail
cd "$(dirname "$0")/.."
cache="${FEDVLA_CACHE:-$HOME/.cache/fedvla}"
export FEDVLA_CACHE="$cache"
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$cache/target}"
export PATH="$cache/tools/bin:$PATH"
mkdir -p "$CARGO_TARGET_DIR"

bash tests/install.sh
# One style (rustfmt.toml), checked first because it is instant.
cargo fmt --check
# The wasm volunteer into www/pkg, which the server serves and the browser tests load.
bash client-wasm/build.sh
# The wasm units (codec, sim, SmolVLA training on the CPU backend and on WebGPU) in a real Chromium.
CHROMEDRIVER="${CHROMEDRIVER:-/usr/bin/chromedriver}" WASM_BINDGEN_TEST_TIMEOUT=600 \
  wasm-pack test --release --headless --chrome client-wasm

# LeRobot 0.6.1 in its chroot (about 100 s the first time, seconds after): it makes the golden fixtures and
# loads our exports in the tests.
lerobot_env="$cache/lerobot-env"
bash ../shared/tools/lerobot-check/setup.sh "$lerobot_env"
# LeRobot's own golden fixtures with several cameras of non-square sizes, made again only when their generator
# changes (about 2 minutes: 7 fixtures).
fixtures="$cache/lerobot-fixtures"
stamp=$(cat tests/lerobot-fixtures/make_fixture.py tests/lerobot-fixtures/make_all.sh | sha256sum | cut -c1-16)
if [[ "$(cat "$fixtures/.stamp" 2>/dev/null)" != "$stamp" ]]; then
  rm -rf "$fixtures"
  LEROBOT_ENV="$lerobot_env" sh tests/lerobot-fixtures/make_all.sh "$fixtures"
  echo "$stamp" >"$fixtures/.stamp"
fi

# Everything native.
FEDVLA_REQUIRE_BROWSER=1 FEDVLA_REQUIRE_AV1=1 FEDVLA_REQUIRE_FIXTURES=1 FEDVLA_LEROBOT_FIXTURES="$fixtures" \
  FEDVLA_LEROBOT_ENV="$lerobot_env" \
  cargo test --workspace --locked --features fedvla-server/av1
