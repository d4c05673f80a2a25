#!/usr/bin/env bash
# What the test command needs on a fresh Debian machine, installed when it is missing (so a second run installs
# nothing): the wasm32 target, rustfmt and clippy, Debian's packages, and the wasm-bindgen and wasm-pack CLIs under
# $FEDVLA_CACHE/tools. Needs root for apt-get when a package is missing. Called by tests/native-env.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
cache="${FEDVLA_CACHE:-$HOME/.cache/fedvla}"
mkdir -p "$cache/tools"
export PATH="$cache/tools/bin:$PATH"

rustup target list --installed | grep -qx wasm32-unknown-unknown || rustup target add wasm32-unknown-unknown
rustup component list --installed | grep -q '^rustfmt' || rustup component add rustfmt
rustup component list --installed | grep -q '^clippy' || rustup component add clippy

# g++/pkg-config: OpenH264 is compiled from its crate's source. Chromium and chromedriver: the browser tests.
# libdav1d-dev: AV1 decoding; ffmpeg (with libsvtav1): encodes the AV1 test clip as LeRobot does.
# debootstrap is not needed: LeRobot's checker fetches its own (../shared/tools/lerobot-check/setup.sh).
packages=(g++ pkg-config chromium chromium-driver libdav1d-dev ffmpeg)
missing=()
for p in "${packages[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
if ((${#missing[@]})); then
  if [[ $(id -u) != 0 ]]; then
    echo "tests/install.sh: missing Debian packages ${missing[*]}; run as root (or apt-get install them)" >&2
    exit 1
  fi
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq "${missing[@]}"
fi

# The wasm-bindgen CLI must be exactly the wasm-bindgen version in Cargo.lock. It is installed without
# --locked: its own lock pins a webpki-roots this registry mirror lacks.
bindgen_version=$(awk '/^name = "wasm-bindgen"$/ { getline; gsub(/"/, "", $3); print $3; exit }' Cargo.lock)
if [[ "$(wasm-bindgen --version 2>/dev/null)" != "wasm-bindgen $bindgen_version" ]]; then
  cargo install --root "$cache/tools" --force wasm-bindgen-cli --version "$bindgen_version"
fi
wasm_pack_version=0.15.1
if [[ "$(wasm-pack --version 2>/dev/null)" != "wasm-pack $wasm_pack_version" ]]; then
  cargo install --root "$cache/tools" --force --locked wasm-pack --version "$wasm_pack_version"
fi
