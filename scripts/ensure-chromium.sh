#!/usr/bin/env bash
# Make sure Debian's chromium and chromedriver are present for the viewer's browser test
# (tests/test_viewer.py drives them headless; nothing is downloaded at test time). Installs them
# with apt when running as root; otherwise says how, and the test skips with one line.
set -eu
have_chromium() {
    { command -v chromium >/dev/null || command -v chromium-browser >/dev/null; } && command -v chromedriver >/dev/null
}
if have_chromium; then exit 0; fi
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "psdr: installing chromium and chromium-driver (the viewer's browser test)"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null || true
    have_chromium && exit 0
fi
echo "psdr: no chromium/chromedriver; the viewer's browser test will skip (install: sudo apt-get install chromium chromium-driver)" >&2
exit 0
