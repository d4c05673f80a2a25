# Sourced by tests/run.sh and tests/coverage.sh: where builds and tools live, what a fresh machine lacks
# (tests/install.sh), and what the native tests read: LeRobot 0.6.1 in the chroot of ../shared/tools/lerobot-check
# (about 100 s the first time, seconds after; it makes the golden fixtures and loads our exports in the tests) and
# LeRobot's own golden fixtures with several cameras of non-square sizes (made again only when their generator
# changes, about 2 minutes: 7 fixtures). Exports the FEDVLA_* switches under which a missing browser, AV1 decoder or
# fixture fails a test instead of skipping it.
cache="${FEDVLA_CACHE:-$HOME/.cache/fedvla}"
export FEDVLA_CACHE="$cache"
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$cache/target}"
export PATH="$cache/tools/bin:$PATH"
mkdir -p "$CARGO_TARGET_DIR"

bash tests/install.sh

lerobot_env="$cache/lerobot-env"
bash ../shared/tools/lerobot-check/setup.sh "$lerobot_env"
fixtures="$cache/lerobot-fixtures"
stamp=$(cat tests/lerobot-fixtures/make_fixture.py tests/lerobot-fixtures/make_all.sh | sha256sum | cut -c1-16)
if [[ "$(cat "$fixtures/.stamp" 2>/dev/null)" != "$stamp" ]]; then
  rm -rf "$fixtures"
  LEROBOT_ENV="$lerobot_env" sh tests/lerobot-fixtures/make_all.sh "$fixtures"
  echo "$stamp" >"$fixtures/.stamp"
fi

export FEDVLA_REQUIRE_BROWSER=1 FEDVLA_REQUIRE_AV1=1 FEDVLA_REQUIRE_FIXTURES=1
export FEDVLA_LEROBOT_FIXTURES="$fixtures" FEDVLA_LEROBOT_ENV="$lerobot_env"
export CHROMEDRIVER="${CHROMEDRIVER:-/usr/bin/chromedriver}"
