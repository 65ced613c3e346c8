#!/usr/bin/env bash
# Build PDAL 2.8.4 and python-pdal 3.4.5 (the versions docker/Dockerfile pins) from their
# sources on Debian 12, and install them beside orchard-trees in a venv: the tiler's
# `--engine pdal` and the PDAL readers of PLY, PCD and text then run (docs/pdal.md).
# PDAL has no PyPI wheel and no Debian 12 package.
#
#   PDAL_GIT=PDAL.git PYPDAL_GIT=python.git [PROJECT=.] [PDAL_ROOT=~/.cache/pdal-build] bench/build_pdal.sh
#
# PDAL_GIT and PYPDAL_GIT: git clones (bare or not) of github.com/PDAL/PDAL and
# github.com/PDAL/python, e.g. `git clone --bare https://github.com/PDAL/PDAL.git`;
# PROJECT: the orchard-trees checkout to install (default: the one holding this script).
# It installs Debian packages (as root) and PyPI packages into the venv; everything else
# goes under PDAL_ROOT: src/, build-pdal/, prefix/ (PDAL), repo/ (a clone of PROJECT),
# venv/. Builds run under `nice -n 19` with JOBS=2 jobs.
# Measured on 2026-11-28 (2 shared cores): apt 85 s, configure 4 s, make -j2 64 min
# (323 compile units), make install 3 s, venv + project 417 s, python-pdal 73 s;
# disk ~1.2 GB (venv 0.9 GB), apt +403 MB.
set -euo pipefail
ROOT=${PDAL_ROOT:-$HOME/.cache/pdal-build}
PDAL_TAG=2.8.4            # needs GDAL >= 3.4 (Debian 12: 3.6.2), PROJ >= 9.0 (9.1.1)
PYPDAL_TAG=3.4.5          # needs PDAL >= 2.6, scikit-build-core < 0.10 (its pyproject sets cmake.verbose)
PDAL_GIT=${PDAL_GIT:?a git clone of github.com/PDAL/PDAL (see the head of this script)}
PYPDAL_GIT=${PYPDAL_GIT:?a git clone of github.com/PDAL/python (see the head of this script)}
PROJECT=${PROJECT:-$(cd "$(dirname "$0")/.." && pwd)}
JOBS=${JOBS:-2}
PREFIX=$ROOT/prefix
VENV=$ROOT/venv
gitdir() { if [ -d "$1/.git" ]; then echo "$1/.git"; else echo "$1"; fi; }
mkdir -p "$ROOT/src"
t() { local s=$SECONDS; "$@"; echo "[time] $((SECONDS-s)) s: $*" >&2; }

# 1. system packages (as root)
t apt-get update -qq
t nice -n 19 apt-get install -y -q --no-install-recommends \
    libgdal-dev libproj-dev libgeotiff-dev libcurl4-openssl-dev libxml2-dev \
    nlohmann-json3-dev libzstd-dev zlib1g-dev liblzma-dev libxerces-c-dev cmake g++ make pkg-config

# 2. PDAL sources. test/data is left out: WITH_TESTS=OFF needs none of it, and a mirror
#    may lack some of its blobs (git archive then dies on them).
rm -rf "$ROOT/src/PDAL-$PDAL_TAG"; mkdir -p "$ROOT/src/PDAL-$PDAL_TAG"
git --git-dir="$(gitdir "$PDAL_GIT")" archive "$PDAL_TAG" -- . ':(exclude)test/data' | tar -x -C "$ROOT/src/PDAL-$PDAL_TAG"

# 3. PDAL: Release, no tests, no plugins. LAZ = vendored lazperf, always built into
#    readers.las/writers.las (no LASzip needed). libpq comes in with libgdal-dev and would
#    switch the pgpointcloud plugin on by itself: turn it off. readers.ply, readers.pcd and
#    readers.text are built in; readers.e57 is a plugin (it needs Xerces-C) and is turned on.
rm -rf "$ROOT/build-pdal"; mkdir -p "$ROOT/build-pdal"; cd "$ROOT/build-pdal"
t nice -n 19 cmake "$ROOT/src/PDAL-$PDAL_TAG" -DCMAKE_BUILD_TYPE=Release \
    -DCMAKE_INSTALL_PREFIX="$PREFIX" -DWITH_TESTS=OFF -DWITH_COMPLETION=OFF \
    -DBUILD_PLUGIN_PGPOINTCLOUD=OFF -DBUILD_PLUGIN_E57=ON
t nice -n 19 make -j"$JOBS"
t nice -n 19 make install
"$PREFIX/bin/pdal" --version
"$PREFIX/bin/pdal" --drivers | grep -E 'readers.las|writers.las|filters.splitter|readers.ply|readers.pcd|readers.text|readers.e57'

# 4. venv with the project and its test extras (a clone, never the checkout itself)
[ -d "$ROOT/repo" ] || git clone -q "$PROJECT" "$ROOT/repo"
python3 -m venv "$VENV"
"$VENV/bin/pip" install -q -U pip
t nice -n 19 "$VENV/bin/pip" install -q -e "$ROOT/repo[test]"

# 5. python-pdal, built against $PREFIX without build isolation (so the scikit-build-core
#    pin holds), with an RPATH to $PREFIX/lib (else: ImportError libpdalcpp.so.18).
rm -rf "$ROOT/src/python-pdal-$PYPDAL_TAG"; mkdir -p "$ROOT/src/python-pdal-$PYPDAL_TAG"
git --git-dir="$(gitdir "$PYPDAL_GIT")" archive "$PYPDAL_TAG" | tar -x -C "$ROOT/src/python-pdal-$PYPDAL_TAG"
"$VENV/bin/pip" install -q "scikit-build-core>=0.9,<0.10" "pybind11[global]"
t env CMAKE_PREFIX_PATH="$PREFIX" PDAL_DIR="$PREFIX/lib/cmake/PDAL" CMAKE_BUILD_PARALLEL_LEVEL="$JOBS" \
    nice -n 19 "$VENV/bin/pip" install --no-build-isolation \
    -C cmake.define.CMAKE_INSTALL_RPATH="$PREFIX/lib" "$ROOT/src/python-pdal-$PYPDAL_TAG"
cd "$ROOT" && "$VENV/bin/python" -c "import pdal; print('python-pdal', pdal.__version__, 'PDAL', pdal.info.version)"
