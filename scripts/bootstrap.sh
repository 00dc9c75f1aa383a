#!/usr/bin/env bash
# Prepare a fresh machine for arcloud: system libraries, then a virtual environment with the pinned
# packages. Idempotent; `make` calls it whenever pyproject.toml or constraints.txt changed.
#   scripts/bootstrap.sh            what `make demo` needs (libusb for open3d)
#   scripts/bootstrap.sh --test     also a redis-server binary for the Redis tests, and Debian's chromium for the
#                                   viewer's browser tests (Playwright drives it; it downloads no browser)
set -euo pipefail
cd "$(dirname "$0")/.."

want_test=0
[[ "${1:-}" == "--test" ]] && want_test=1
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}

say() { printf 'bootstrap: %s\n' "$*" >&2; }

# --- system packages -------------------------------------------------------------------------------
missing=()
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
ldconfig -p 2>/dev/null | grep -q 'libgomp.so.1' || missing+=(libgomp1)
if (( want_test )) && ! command -v redis-server >/dev/null 2>&1; then missing+=(redis-server); fi
if (( want_test )) && ! command -v chromium >/dev/null 2>&1; then missing+=(chromium); fi
if (( ${#missing[@]} )); then
  sudo=""
  [[ $(id -u) -ne 0 ]] && command -v sudo >/dev/null 2>&1 && sudo="sudo -n"
  if command -v apt-get >/dev/null 2>&1 && { [[ $(id -u) -eq 0 ]] || [[ -n "$sudo" ]]; }; then
    say "installing system packages: ${missing[*]}"
    $sudo apt-get update -qq >/dev/null
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
    if [[ -z "$sudo" ]] && (( want_test )) && command -v redis-server >/dev/null 2>&1; then
      # Debian starts a system Redis on 6379 when it installs one; the tests start their own on free ports.
      (service redis-server stop >/dev/null 2>&1 || true)
    fi
  else
    say "missing system packages: ${missing[*]}"
    say "install them with your package manager (Debian/Ubuntu: sudo apt-get install ${missing[*]}), then run make again."
    exit 1
  fi
fi

# --- Python ----------------------------------------------------------------------------------------
if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
  say "arcloud needs Python >= 3.11; '$PYTHON' is $("$PYTHON" --version 2>&1 || echo missing). Set PYTHON=/path/to/python3.11."
  exit 1
fi
if [[ ! -x "$VENV/bin/python" ]]; then
  say "creating virtual environment $VENV"
  "$PYTHON" -m venv "$VENV"
fi
say "installing pinned packages (constraints.txt) into $VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip >/dev/null 2>&1 || true
"$VENV/bin/python" -m pip install -q -c constraints.txt -e '.[all,dev]' 2>&1 | grep -v "^WARNING: Location" || true
"$VENV/bin/python" -c 'import arcloud, open3d, onnxruntime, zenoh' || { say "the environment does not import; see the errors above"; exit 1; }
touch "$VENV/.installed"
