#!/usr/bin/env bash
# Prepares a fresh Debian bookworm machine for lerobot-roboscape: system libraries, uv, and the project's
# environment from uv.lock. Safe to run again: every step checks before it acts.
set -euo pipefail
cd "$(dirname "$0")/.."

as_root() { if [ "$(id -u)" -eq 0 ]; then "$@"; else sudo "$@"; fi; }

# ManiSkill (SAPIEN) needs a Vulkan device even without cameras. With no GPU driver the only one is Mesa's
# software renderer (lavapipe), and bookworm's Mesa 22 is too old for SAPIEN: take Mesa >= 24.3 from
# bookworm-backports, served by the same mirror the machine already uses.
if command -v apt-get >/dev/null 2>&1; then
  if ! dpkg -s mesa-vulkan-drivers 2>/dev/null | grep -qE '^Version: (2[4-9]|[3-9][0-9])'; then
    sources=$(ls /etc/apt/sources.list /etc/apt/sources.list.d/* 2>/dev/null || true)
    if ! grep -qs 'bookworm-backports' $sources; then
      mirror=$(grep -hoE '^(URIs: |deb )\S+/debian/?( |$)' $sources | head -n1 | sed -E 's/^(URIs: |deb )//; s/ *$//' || true)
      [ -n "$mirror" ] || { echo "setup: no Debian mirror found in /etc/apt sources" >&2; exit 1; }
      echo "deb $mirror bookworm-backports main" | as_root tee /etc/apt/sources.list.d/roboscape-backports.list >/dev/null
    fi
    as_root apt-get update -qq
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq -t bookworm-backports \
      mesa-vulkan-drivers libvulkan1 libegl1 >/dev/null
  fi
  # FFmpeg shared libraries for torchcodec (LeRobot's video decoder).
  if ! dpkg -s libavcodec59 libavformat59 libavfilter8 libavdevice59 >/dev/null 2>&1; then
    as_root apt-get update -qq
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
      libavcodec59 libavformat59 libavutil57 libswscale6 libswresample4 libavfilter8 libavdevice59 >/dev/null
  fi
fi

command -v uv >/dev/null 2>&1 || python3 -m pip install -q uv

# The project needs Python 3.12; uv cannot download interpreters here, so point it at a local one.
if [ -z "${UV_PYTHON:-}" ]; then
  for candidate in python3.12 "$(command -v pyenv >/dev/null 2>&1 && pyenv root)"/versions/3.12*/bin/python3.12; do
    if "$candidate" -c 'import sys; assert sys.version_info[:2] == (3, 12)' >/dev/null 2>&1; then
      export UV_PYTHON="$candidate"; break
    fi
  done
fi
# Bytecode compiled once at install: with PYTHONDONTWRITEBYTECODE set (as on CI), every process would otherwise
# recompile torch, lerobot and mani_skill from source on import (about 25 s each instead of 5).
uv sync --locked --quiet --compile-bytecode ${UV_PYTHON:+--python "$UV_PYTHON"}
