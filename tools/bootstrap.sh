#!/usr/bin/env bash
# Bootstrap the LSU workspace on a bare Debian 12 + Python 3.11 machine (run by `make setup`).
#
# Steps (each skipped when its inputs did not change, so a second run takes seconds):
#   1. system packages (apt, only what wheels cannot give: compiler, cmake, venv, libusb, sdcc + ucsim)
#   2. .venv with the pinned requirements.lock
#   3. path fixes in the ROS wheels' cmake files (they name the wheel builder's Python)
#   4. colcon build of src/lsu_interfaces and src/tf2_msgs (not on PyPI) straight into .venv (no sourcing needed)
#   5. editable installs of the ament_python packages (node executables in .venv/bin)
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
VENV="$ROOT/.venv"
STAMPS="$VENV/.lsu-stamps"
PYTHON="${PYTHON:-python3}"
# every ament_python package under src/ (a new package needs no edit here)
PY_PACKAGES=()
for setup_py in "$ROOT"/src/*/setup.py; do PY_PACKAGES+=("$(basename "$(dirname "$setup_py")")"); done

step=""
fail() {
    echo "[setup] FAILED at step '$step': $1" >&2
    echo "[setup] what to do: $2" >&2
    exit 1
}
trap 'rc=$?; [ $rc -eq 0 ] || [ -z "$step" ] || echo "[setup] step \"$step\" exited with $rc; see the output above." >&2' EXIT
say() { echo "[setup] $*"; }

# hash of files (paths relative to ROOT), used as the stamp of a step's inputs
inputs_hash() { (cd "$ROOT" && find "$@" -type f ! -name '*.pyc' ! -path '*/__pycache__/*' -print0 | sort -z | xargs -0 sha256sum | sha256sum | cut -c1-64); }
stamp_ok() { [ -f "$STAMPS/$1" ] && [ "$(cat "$STAMPS/$1")" = "$2" ]; }
stamp_set() { mkdir -p "$STAMPS"; echo "$2" > "$STAMPS/$1"; }

# ---------------------------------------------------------------- 1. system packages
step="system packages"
command -v "$PYTHON" >/dev/null || fail "'$PYTHON' not found" "install Python 3.11 (Debian 12: apt-get install python3) or set PYTHON=/path/to/python3.11"
pyver="$("$PYTHON" -c 'import sys; print("%d.%d" % sys.version_info[:2])')"
[ "$pyver" = "3.11" ] || fail "$PYTHON is Python $pyver; the ROS 2 Jazzy wheels need 3.11" "run with PYTHON=/path/to/python3.11"
missing=()
command -v cmake >/dev/null || missing+=(cmake)
command -v c++ >/dev/null || missing+=(g++)
command -v make >/dev/null || missing+=(make)
# ip (iproute2): the two-host test makes network namespaces with it
command -v ip >/dev/null || missing+=(iproute2)
"$PYTHON" -c 'import ensurepip, venv' 2>/dev/null || missing+=(python3-venv)
# open3d needs libusb-1.0.so.0 at import time; no wheel ships it
if ! ldconfig -p 2>/dev/null | grep 'libusb-1.0.so.0' >/dev/null; then missing+=(libusb-1.0-0); fi  # no -q: SIGPIPE + pipefail
# the GP32 firmware: compiler and HC08 simulator (lsu gp32 firmware build|run)
command -v sdcc >/dev/null || missing+=(sdcc)
command -v shc08 >/dev/null || missing+=(sdcc-ucsim)
# the web page's browser tests: Debian's chromium, driven by Playwright (which downloads no browser)
command -v chromium >/dev/null || missing+=(chromium)
if [ ${#missing[@]} -gt 0 ]; then
    say "installing Debian packages: ${missing[*]}"
    if [ "$(id -u)" != 0 ]; then
        fail "missing Debian packages: ${missing[*]}" "run: sudo apt-get install -y ${missing[*]}   (then make setup again)"
    fi
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq || fail "apt-get update failed" "check the network / apt sources, then make setup again"
    apt-get install -y -qq "${missing[@]}" >/dev/null || fail "apt-get install ${missing[*]} failed" "install them by hand, then make setup again"
fi

# ---------------------------------------------------------------- 2. venv + pinned wheels
step="python environment"
if [ ! -x "$VENV/bin/python" ]; then
    say "creating $VENV"
    "$PYTHON" -m venv "$VENV" || fail "python -m venv failed" "apt-get install python3-venv, remove .venv, make setup again"
fi
lock_hash="$(inputs_hash requirements.lock)"
if ! stamp_ok lock "$lock_hash"; then
    say "installing pinned wheels from requirements.lock (first time: ~2 min)"
    # uv (pinned in the lock) installs the set: it downloads in parallel and compiles the bytecode on
    # every core, where pip does both one file at a time (about 3x the wall time on 2 cores). The lock
    # pins every distribution, so uv resolves nothing new; the bytecode matters because make exports
    # PYTHONDONTWRITEBYTECODE (without it every node process would compile its imports again).
    uv_pin="$(grep -E '^uv==' requirements.lock)" || fail "requirements.lock pins no uv" "run make lock (requirements.in lists uv)"
    "$VENV/bin/python" -m pip install -q --disable-pip-version-check "$uv_pin" 2>&1 \
        | grep -v -E "^WARNING: Location .* is ignored" || true
    [ -x "$VENV/bin/uv" ] || fail "$uv_pin did not install (see pip output above)" "check network access to PyPI; remove .venv and make setup again"
    "$VENV/bin/uv" pip install -q --python "$VENV/bin/python" --compile-bytecode -r requirements.lock \
        || fail "uv could not install requirements.lock (see its output above)" "check network access to PyPI; remove .venv and make setup again"
    "$VENV/bin/python" -c 'import rclpy, numpy, scipy, cv2, serial, rosbags, yaml, pytest' \
        || fail "the pinned wheels did not install (see pip output above)" "check network access to PyPI; remove .venv and make setup again"
    rm -f "$STAMPS/pathfix" "$STAMPS/interfaces" "$STAMPS/packages"
    stamp_set lock "$lock_hash"
fi

# ---------------------------------------------------------------- 3. path fixes
step="cmake path fixes"
if ! stamp_ok pathfix "$lock_hash"; then
    py_inc="$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
    np_inc="$("$VENV/bin/python" -c 'import numpy; print(numpy.get_include())')"
    [ -f "$py_inc/Python.h" ] || fail "Python headers not found in $py_inc" "apt-get install python3-dev (or use a Python with headers), then make setup again"
    n=0
    while IFS= read -r -d '' f; do
        sed -i -e "s#/opt/python/cp311-cp311/include/python3.11#$py_inc#g" \
               -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$np_inc#g" "$f"
        n=$((n + 1))
    done < <(grep -rlZ --include='*.cmake' -e /opt/python/cp311-cp311 "$VENV" 2>/dev/null || true)
    say "rewrote wheel-builder paths in $n cmake files"
    stamp_set pathfix "$lock_hash"
fi

# ---------------------------------------------------------------- 4. lsu_interfaces
step="build lsu_interfaces"
if_hash="$(inputs_hash src/lsu_interfaces src/tf2_msgs requirements.lock)"
if ! stamp_ok interfaces "$if_hash" || ! "$VENV/bin/python" -c 'import lsu_interfaces.msg, tf2_msgs.msg' 2>/dev/null; then
    # LSU_PYTHON_ONLY: only the C and Python generators and typesupports (every node is rclpy); the C++
    # ones would double the compile time. A ROS workspace building these packages gets all of them.
    say "building lsu_interfaces and tf2_msgs with colcon into .venv (~60 s)"
    mkdir -p "$ROOT/log"
    # MAKEFLAGS with -j: colcon then adds no "-l <cores>" load limit, which on a busy host builds one job at a time
    if ! env -i HOME="${HOME:-/root}" PATH="$VENV/bin:/usr/local/bin:/usr/bin:/bin" LANG=C.UTF-8 \
        MAKEFLAGS="-j$(nproc)" VIRTUAL_ENV="$VENV" AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV" \
        "$VENV/bin/colcon" --log-base "$ROOT/log" build --base-paths "$ROOT/src/lsu_interfaces" "$ROOT/src/tf2_msgs" \
        --build-base "$ROOT/build" --merge-install --install-base "$VENV" \
        --packages-select lsu_interfaces tf2_msgs --event-handlers console_cohesion- summary- \
        --cmake-args -DBUILD_TESTING=OFF -DLSU_PYTHON_ONLY=ON > "$ROOT/log/interfaces-build.txt" 2>&1; then
        tail -n 30 "$ROOT/log/interfaces-build.txt" >&2 || true
        fail "colcon build of lsu_interfaces failed (full log: log/interfaces-build.txt)" \
             "fix the .msg/.srv/.action named in the log, or remove build/ and .venv and make setup again"
    fi
    env -i "$VENV/bin/python" -c 'from lsu_interfaces.msg import LaserLine; from lsu_interfaces.action import Scan; from tf2_msgs.msg import TFMessage' \
        || fail "lsu_interfaces built but does not import" "remove build/ and make setup again"
    stamp_set interfaces "$if_hash"
fi

# ---------------------------------------------------------------- 5. ament_python packages
step="install python packages"
pkg_hash="$(inputs_hash $(for p in "${PY_PACKAGES[@]}"; do echo "src/$p/setup.py" "src/$p/setup.cfg" "src/$p/package.xml"; done) requirements.lock)"
if ! stamp_ok packages "$pkg_hash"; then
    say "installing ${PY_PACKAGES[*]} in editable mode"
    # packages this checkout no longer has (renamed or split) must not linger with their entry points
    stale="$("$VENV/bin/python" -c 'import sys, importlib.metadata as md; keep = set(sys.argv[1:]) | {"lsu_interfaces"}
print(" ".join(sorted({n for n in (str(d.metadata["Name"] or "").replace("-", "_") for d in md.distributions())
                       if n.startswith("lsu_") and n not in keep})))' "${PY_PACKAGES[@]}")"
    [ -z "$stale" ] || "$VENV/bin/python" -m pip uninstall -q -y $stale
    args=()
    for p in "${PY_PACKAGES[@]}"; do args+=(-e "src/$p"); done
    # no build isolation: the pinned setuptools in .venv builds them (isolation would fetch and install
    # setuptools into a throw-away environment once per package)
    "$VENV/bin/python" -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation "${args[@]}" 2>&1 \
        | grep -v -E "^WARNING: Location .* is ignored" || true
    [ -x "$VENV/bin/lsu" ] || fail "the lsu command was not installed" "see the pip output above"
    stamp_set packages "$pkg_hash"
fi
step=""
say "ready: $VENV (lsu, node executables and lsu_interfaces need no sourcing)"
