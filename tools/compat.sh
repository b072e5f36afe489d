#!/usr/bin/env bash
# Builds a LeRobot 0.6 environment beside the checkout, in .compat/ (kept until `make clean`):
# a Debian 13 root filesystem (Python 3.13: LeRobot 0.5 and later need 3.12 or newer, this
# machine's Python is 3.11), a virtualenv inside it with lerobot==$LEROBOT_VERSION, and
# .compat/python, a wrapper that runs that Python from this machine through the tree's own
# loader. Each step is skipped when its result is already there. specs/policy.md says why.
set -euo pipefail
cd "$(dirname "$0")/.."
LEROBOT_VERSION=${LEROBOT_VERSION:-0.6.1}
DIR=${COMPAT_DIR:-$PWD/.compat}
ROOT=$DIR/root
SUDO=$([ "$(id -u)" = 0 ] || echo sudo)
mkdir -p "$DIR"
if [ ! -x "$ROOT/usr/bin/python3" ]; then
    command -v debootstrap >/dev/null || {
        $SUDO apt-get update -qq
        DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq debootstrap >/dev/null
    }
    rm -rf "$ROOT"
    $SUDO debootstrap --variant=minbase --include=python3,python3-venv trixie "$ROOT" \
        http://deb.debian.org/debian >"$DIR/debootstrap.log"
fi
for LOADER in "$ROOT"/lib64/ld-linux-x86-64.so.2 "$ROOT"/lib/ld-linux-aarch64.so.1; do
    [ -e "$LOADER" ] && break
done
LIBS=$ROOT/lib/$(uname -m)-linux-gnu:$ROOT/usr/lib/$(uname -m)-linux-gnu
PYVER=$(ls "$ROOT/usr/lib" | grep -E '^python3\.[0-9]+$' | sort -V | tail -1)
# The virtualenv's Python, run from this machine through the tree's own loader and libraries
# (a program of the tree cannot start on this machine's loader); started by its path in the
# virtualenv, it finds the virtualenv (pyvenv.cfg) and the tree's standard library.
cat >"$DIR/python" <<WRAP
#!/bin/sh
# LeRobot's Python, in $ROOT (tools/compat.sh made this).
exec $LOADER --library-path $LIBS $DIR/venv/bin/$PYVER "\$@"
WRAP
chmod +x "$DIR/python"
if [ ! -e "$DIR/venv/bin/$PYVER" ]; then
    PYTHONHOME=$ROOT/usr $LOADER --library-path "$LIBS" "$ROOT/usr/bin/$PYVER" \
        -m venv --without-pip "$DIR/venv"
fi
if [ ! -e "$DIR/venv/.installed-$LEROBOT_VERSION-dataset-diffusion-feetech" ]; then
    cp /etc/ssl/certs/ca-certificates.crt "$DIR/ca.crt"
    export PIP_CERT=$DIR/ca.crt SSL_CERT_FILE=$DIR/ca.crt PIP_CONFIG_FILE=/dev/null \
        PIP_DISABLE_PIP_VERSION_CHECK=1
    # ensurepip would start the virtualenv's Python without the loader: pip from its wheel.
    if ! "$DIR/python" -m pip --version >/dev/null 2>&1; then
        rm -rf "$DIR/wheels"
        # (a mirror may answer with addresses relative to the page: joined to it)
        "$DIR/python" -c 'import sys, urllib.parse, urllib.request, json
page = "https://pypi.org/pypi/pip/json"
info = json.load(urllib.request.urlopen(page))
wheel = next(f for f in info["urls"] if f["filename"].endswith(".whl"))
url = urllib.parse.urljoin(page, wheel["url"])
urllib.request.urlretrieve(url, sys.argv[1] + "/" + wheel["filename"])' \
            "$(mkdir -p "$DIR/wheels" && echo "$DIR/wheels")"
        WHEEL=$(echo "$DIR"/wheels/pip-*.whl)
        "$DIR/python" "$WHEEL/pip" install --quiet --no-index "$WHEEL"
    fi
    # The feetech extra (`arena bench teleop` runs LeRobot's SO-101 loop): its servo SDK is a
    # source package, whose build pip would run in a Python started without the loader; this
    # machine's Python builds its (pure Python) wheel instead.
    HOST_PYTHON=${HOST_PYTHON:-$( [ -x .venv/bin/python ] && echo .venv/bin/python || echo python3)}
    "$HOST_PYTHON" -m pip wheel --quiet --no-deps -w "$DIR/wheels" "feetech-servo-sdk>=1.0.0,<2.0.0"
    "$DIR/python" -m pip install --quiet --find-links "$DIR/wheels" \
        "lerobot[dataset,diffusion,feetech]==$LEROBOT_VERSION" msgspec
    touch "$DIR/venv/.installed-$LEROBOT_VERSION-dataset-diffusion-feetech"
fi
"$DIR/python" -c 'import lerobot, sys; print("LeRobot", lerobot.__version__, "on Python", sys.version.split()[0])'
