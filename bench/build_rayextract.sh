#!/usr/bin/env bash
# Build raycloudtools' `rayextract` (the reference of bench/rayextract.py and
# bench/density.py) from its sources, with only what `rayextract trees` needs.
#
#   bench/build_rayextract.sh RAYCLOUDTOOLS_SRC LIBNABO_SRC [BUILD_DIR]
#
# It downloads nothing. Get the two source trees first, for example:
#   git clone https://github.com/csiro-robotics/raycloudtools.git
#   git clone https://github.com/ethz-asl/libnabo.git && git -C libnabo checkout tags/1.0.7
# (1.0.7 is the libnabo tag raycloudtools' README names.) Or from bare mirrors:
#   git --git-dir=MIRROR archive HEAD | tar -x -C SRC
#
# The only things it installs are Debian packages (cmake, g++, libeigen3-dev), and only
# when they are missing and it runs as root; libnabo goes into BUILD_DIR/prefix, not the
# system. raycloudtools' optional dependencies (LASzip, Qhull, TIFF/GeoTIFF, TBB) stay
# off: `rayextract trees` reads PLY and needs none of them. Builds run under
# `nice -n 10` with 2 jobs (JOBS=N to change). The last line printed is the binary's path.
set -euo pipefail

if [[ $# -lt 2 || $# -gt 3 ]]; then
    sed -n '2,11p' "$0" | sed 's/^# \{0,1\}//' >&2
    exit 2
fi
rct_src=$(realpath "$1")
nabo_src=$(realpath "$2")
build=$(realpath -m "${3:-/tmp/build/rayextract}")
jobs=${JOBS:-2}
for f in "$rct_src/raycloudtools/rayextract/rayextract.cpp" "$nabo_src/nabo/nabo.h"; do
    if [[ ! -f $f ]]; then
        echo "error: $f not found: give the raycloudtools and libnabo source folders" >&2
        exit 2
    fi
done

missing=()
command -v cmake >/dev/null || missing+=(cmake)
command -v g++ >/dev/null || missing+=(g++)
[[ -f /usr/include/eigen3/Eigen/Core ]] || missing+=(libeigen3-dev)
if [[ ${#missing[@]} -gt 0 ]]; then
    if [[ $(id -u) -ne 0 ]]; then
        echo "error: missing ${missing[*]}: run 'apt-get install ${missing[*]}' as root" >&2
        exit 1
    fi
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
fi

prefix=$build/prefix
mkdir -p "$build/libnabo" "$build/raycloudtools" "$prefix"

# libnabo: the static library and its CMake config only (no tests, examples, Python).
nice -n 10 cmake -S "$nabo_src" -B "$build/libnabo" -DCMAKE_BUILD_TYPE=Release \
    -DCMAKE_INSTALL_PREFIX="$prefix" -DCMAKE_EXPORT_NO_PACKAGE_REGISTRY=ON -DUSE_OPEN_CL=FALSE >"$build/libnabo.cmake.log" 2>&1
nice -n 10 cmake --build "$build/libnabo" --target nabo -j "$jobs" >"$build/libnabo.build.log"
# `install` would build every target (tests, python); copy what find_package needs instead
nice -n 10 cmake --install "$build/libnabo" >"$build/libnabo.install.log" 2>&1 || {
    install -D -m 644 "$build/libnabo/libnabo.a" "$prefix/lib/libnabo.a"
    install -D -m 644 "$nabo_src/nabo/nabo.h" "$prefix/include/nabo/nabo.h"
    install -D -m 644 "$nabo_src/nabo/third_party/any.hpp" "$prefix/include/nabo/third_party/any.hpp"
}

# raycloudtools: the rayextract target only, optional dependencies off.
nice -n 10 cmake -S "$rct_src" -B "$build/raycloudtools" -DCMAKE_BUILD_TYPE=Release \
    -DCMAKE_PREFIX_PATH="$prefix" -Dlibnabo_DIR="$build/libnabo" \
    -DRAYCLOUD_BUILD_TESTS=OFF -DRAYLIB_WITH_LAS=OFF -DRAYLIB_WITH_QHULL=OFF -DRAYLIB_WITH_TIFF=OFF \
    -DRAYLIB_WITH_TBB=OFF -DRAYLIB_WITH_NORMAL_FIELD=ON >"$build/raycloudtools.cmake.log" 2>&1
nice -n 10 cmake --build "$build/raycloudtools" --target rayextract -j "$jobs" >"$build/raycloudtools.build.log"

binary=$(find "$build/raycloudtools" -name rayextract -xtype f -perm -u+x | head -n 1)
if [[ -z $binary ]]; then
    echo "error: the build finished without a rayextract binary; see $build/*.log" >&2
    exit 1
fi
echo "$binary"
