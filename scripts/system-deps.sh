#!/bin/sh
# The system (Debian) packages `make demo` and `make test` need, installed when missing. The Makefile (before
# building .venv) and .ci/run call this one script; nothing else installs system packages.
#
#   espeak-ng       libespeak-ng.so.1: the synthetic scale corpus (`visemeflow espeak-corpus`) and tests/test_espeak.py
#   chromium        headless browser of tests/test_dashboard.py (opens the HTML dashboard)
#   nodejs, npm     Node for the Khronos glTF validator (npm `gltf-validator`) of the animation stages
#   klettres-data   real syllables spoken in 16 languages (KDE's KLettres, GPL-2+, read where installed, never
#                   copied): tests/test_syllables.py and bench/syllables.py judge the default model's lips on them
#   curl            the README's raw-HTTP lines to `visemeflow serve`, run as written by tests/test_security.py
#   fonts-droid-fallback  a CJK font (Apache-2.0, 4 MB) for the dashboard's charts: a Mandarin utterance id is drawn
#                   in characters, not boxes (visemeflow/dashboards/plots.py)
#
# All present: exit 0 at once, no apt call. Missing, as root: apt-get update + install, then check again.
# Missing, not root: one line on stderr naming the packages and the command that installs them, exit 1.
set -eu

missing=""
need() { case " $missing " in *" $1 "*) ;; *) missing="${missing:+$missing }$1" ;; esac; }
have() { command -v "$1" >/dev/null 2>&1; }

check() {
    missing=""
    # ldconfig lives in /sbin, which a normal user's PATH often lacks.
    ldconfig=""
    for candidate in "$(command -v ldconfig 2>/dev/null || true)" /sbin/ldconfig /usr/sbin/ldconfig; do
        if [ -n "$candidate" ] && [ -x "$candidate" ]; then ldconfig=$candidate; break; fi
    done
    case "$( [ -n "$ldconfig" ] && "$ldconfig" -p 2>/dev/null || true)" in
        *libespeak-ng.so.1*) ;;
        *) need espeak-ng ;;
    esac
    have chromium || have chromium-browser || have google-chrome || need chromium
    have node || { need nodejs; need npm; }
    have npm || need npm
    [ -f /usr/share/klettres/fr/sounds.xml ] || need klettres-data
    have curl || need curl
    [ -f /usr/share/fonts/truetype/droid/DroidSansFallbackFull.ttf ] || need fonts-droid-fallback
}

check
[ -z "$missing" ] && exit 0

command="apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y $missing"
if [ "$(id -u 2>/dev/null || echo unknown)" != 0 ]; then
    echo "system packages missing: $missing; install them with: sudo sh -c '$command'" >&2
    exit 1
fi
if ! have apt-get; then
    echo "system packages missing: $missing; no apt-get here: install the equivalents of Debian's $missing" >&2
    exit 1
fi
echo "installing system packages: $missing" >&2
apt-get update -qq >/dev/null
# shellcheck disable=SC2086  # one word per package
DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $missing >/dev/null
wanted=$missing
check
if [ -n "$missing" ]; then
    echo "system packages still missing after apt-get install -y $wanted: $missing" >&2
    exit 1
fi
