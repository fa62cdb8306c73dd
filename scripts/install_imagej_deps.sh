#!/bin/sh
# Install what the ImageJ test harness (tests/imagej/) needs on Debian/Ubuntu: ImageJ 1.x
# (/usr/share/java/ij.jar), Jython 2.7 (/usr/share/java/jython.jar), Xvfb, a JDK (javac) and a font;
# for the user's-session tests (test_gui_session.py) a window manager, xdotool, xwd and ImageMagick;
# for the painting report's zoomable view (tests/test_painting.py) a headless browser, Debian's chromium.
# No-op when everything is present; installs with apt-get when run as root or when sudo works
# without a password; otherwise says what to run and exits 1. See docs in tests/imagej/README.md.
set -eu

PACKAGES="imagej jython xvfb default-jdk-headless fonts-dejavu-core openbox xdotool x11-apps imagemagick chromium"

have_all() {
    [ -f /usr/share/java/ij.jar ] && [ -f /usr/share/java/jython.jar ] \
        && command -v java >/dev/null 2>&1 && command -v javac >/dev/null 2>&1 \
        && command -v Xvfb >/dev/null 2>&1 \
        && command -v openbox >/dev/null 2>&1 && command -v xdotool >/dev/null 2>&1 \
        && command -v xwd >/dev/null 2>&1 && command -v convert >/dev/null 2>&1 \
        && command -v chromium >/dev/null 2>&1 \
        && { [ -d /usr/share/fonts/truetype/dejavu ] || [ -d /usr/share/fonts/dejavu ]; }
}

if have_all; then
    exit 0
fi

if [ "$(id -u)" -eq 0 ]; then
    SUDO=""
elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    SUDO="sudo -n"
else
    echo "install_imagej_deps.sh: ImageJ test dependencies are missing and this user cannot" >&2
    echo "install them; run as root: apt-get update && apt-get install -y $PACKAGES" >&2
    exit 1
fi

if ! command -v apt-get >/dev/null 2>&1; then
    echo "install_imagej_deps.sh: apt-get not found; install these Debian packages or their" >&2
    echo "equivalents by hand: $PACKAGES" >&2
    exit 1
fi

echo "install_imagej_deps.sh: installing $PACKAGES" >&2
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq >/dev/null
# shellcheck disable=SC2086  # word splitting of the package list is intended
$SUDO apt-get install -y -qq --no-install-recommends $PACKAGES >/dev/null

if ! have_all; then
    echo "install_imagej_deps.sh: installed $PACKAGES but ij.jar, jython.jar, javac or Xvfb is" >&2
    echo "still missing" >&2
    exit 1
fi
