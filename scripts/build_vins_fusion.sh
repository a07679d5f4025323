#!/usr/bin/env bash
# Build the stock VINS-Fusion estimator (ROS 1, `vins_node`) on Debian 12 from Debian's own ROS 1
# packages, to score feature bags with (docs/vins_fusion.md, "Building the estimator").
#
#   scripts/build_vins_fusion.sh [WORKSPACE]            # default: $HOME/vins_ws
#
# Options (or the environment variable in brackets):
#   --src DIR    a VINS-Fusion checkout, or a bare git repository of it            [VINS_SRC]
#   --git URL    clone this repository when --src is not given                      [VINS_GIT_URL]
#   --rev REV    the commit to build (from a git repository; default: the one below)  [VINS_REV]
#   --jobs N     parallel compile jobs (default 2)                                   [VINS_JOBS]
#   --no-apt     do not install Debian packages (they must be there already)         [VINS_NO_APT=1]
#   --yaw-gauge  also hold the window's yaw without Euler angles (an estimator change:  [VINS_YAW_GAUGE=1]
#                scripts/vins_fusion_yaw_gauge.patch, docs/scenes.md); build it into its own workspace
#
# Without --yaw-gauge, only two changes to upstream, both needed by Debian 12's toolchain, nothing that
# alters the estimator:
#   1. OpenCV 4 dropped the C API's constant names (CV_LOAD_IMAGE_GRAYSCALE, CV_AA, CV_GRAY2RGB, ...):
#      they become their cv:: names (scripts/vins_fusion_opencv4.sed);
#   2. `-std=c++11` becomes `-std=c++17` (Debian's Ceres 2.1 and its headers need C++14 or later).
# Only the `vins` package (vins_estimator/) and what it links, camera_models/, are built, and of them only
# the target vins_node (not the KITTI test programs, not the calibration tool); loop_fusion and
# global_fusion are not needed to score trajectories.
#
# Idempotent: a second run installs nothing, leaves an unchanged source tree untouched (so make rebuilds
# nothing) and prints the same path.
set -euo pipefail

# The commit the project's figures were made with: upstream master "fix a memory issue" (2021-07-26).
DEFAULT_REV=be55a937a57436548ddfb1bd324bc1e9a9e828e0
DEFAULT_GIT_URL=https://github.com/HKUST-Aerial-Robotics/VINS-Fusion.git

SCRIPT_DIR=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
SED_SCRIPT="$SCRIPT_DIR/vins_fusion_opencv4.sed"
YAW_PATCH="$SCRIPT_DIR/vins_fusion_yaw_gauge.patch"

SRC=${VINS_SRC:-}
GIT_URL=${VINS_GIT_URL:-$DEFAULT_GIT_URL}
REV=${VINS_REV:-}
JOBS=${VINS_JOBS:-2}
NO_APT=${VINS_NO_APT:-0}
YAW_GAUGE=${VINS_YAW_GAUGE:-0}
WS=""

usage() { sed -n '2,14p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'; }
die() { echo "build_vins_fusion: $*" >&2; exit 1; }

while [[ $# -gt 0 ]]; do
    case "$1" in
        --src) SRC=${2:?--src needs a folder}; shift 2 ;;
        --git) GIT_URL=${2:?--git needs a URL}; shift 2 ;;
        --rev) REV=${2:?--rev needs a commit}; shift 2 ;;
        --jobs) JOBS=${2:?--jobs needs a number}; shift 2 ;;
        --no-apt) NO_APT=1; shift ;;
        --yaw-gauge) YAW_GAUGE=1; shift ;;
        -h|--help) usage; exit 0 ;;
        -*) die "unknown option $1 (see --help)" ;;
        *) [[ -z "$WS" ]] || die "one workspace folder only (got '$WS' and '$1')"; WS=$1; shift ;;
    esac
done
WS=${WS:-$HOME/vins_ws}
mkdir -p "$WS"
WS=$(cd "$WS" && pwd)
[[ -f "$SED_SCRIPT" ]] || die "missing $SED_SCRIPT (run the script from its repository)"
[[ "$YAW_GAUGE" != 1 || -f "$YAW_PATCH" ]] || die "missing $YAW_PATCH (run the script from its repository)"

# ---- 1. Debian packages -------------------------------------------------------------------------------
# ROS 1 Noetic-era packages as Debian 12 ships them (under /usr, no /opt/ros): catkin and roscpp with the
# message headers vins_node includes, cv_bridge, image_transport, tf; Ceres, Eigen, OpenCV, Boost (for
# camera_models); roscore and rosbag play to run it.
PACKAGES=(
    build-essential cmake git catkin
    libroscpp-dev libstd-msgs-dev libgeometry-msgs-dev libnav-msgs-dev libsensor-msgs-dev
    libvisualization-msgs-dev libcv-bridge-dev libimage-transport-dev libtf-dev
    libceres-dev libeigen3-dev libopencv-dev libboost-filesystem-dev libboost-program-options-dev
    ros-core-dev python3-roslaunch python3-rosbag
)
missing=()
for pkg in "${PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [[ ${#missing[@]} -gt 0 ]]; then
    [[ "$NO_APT" == 1 ]] && die "missing Debian packages (and --no-apt given): ${missing[*]}"
    SUDO=""
    [[ $(id -u) -eq 0 ]] || SUDO=sudo
    echo "build_vins_fusion: installing ${missing[*]}"
    $SUDO apt-get update
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y --no-install-recommends "${missing[@]}"
fi

# ---- 2. The source: camera_models/ and vins_estimator/ at the chosen commit ------------------------------
STAGE=$(mktemp -d "$WS/.stage.XXXXXX")
trap 'rm -rf "$STAGE"' EXIT
from_git() {  # $1: a git directory (bare or .git); exports the two folders at $REV
    local gitdir=$1 rev=${REV:-$DEFAULT_REV}
    git --git-dir="$gitdir" cat-file -e "$rev^{commit}" 2>/dev/null \
        || die "commit $rev is not in $gitdir (give --rev, or fetch it)"
    git --git-dir="$gitdir" archive "$rev" -- camera_models vins_estimator | tar -x -C "$STAGE"
    echo "build_vins_fusion: source $gitdir at $rev"
}
if [[ -n "$SRC" ]]; then
    [[ -d "$SRC" ]] || die "--src $SRC: no such folder"
    SRC=$(cd "$SRC" && pwd)
    if [[ -d "$SRC/vins_estimator" && -d "$SRC/camera_models" ]]; then
        [[ -z "$REV" ]] || die "--rev applies to a git repository; $SRC is a checkout: check the commit out there"
        cp -a "$SRC/camera_models" "$SRC/vins_estimator" "$STAGE/"
        echo "build_vins_fusion: source $SRC (as it is checked out)"
    elif git --git-dir="$SRC" rev-parse --git-dir >/dev/null 2>&1; then
        from_git "$SRC"
    else
        die "--src $SRC has neither vins_estimator/ and camera_models/ nor a git repository"
    fi
else
    CLONE="$WS/upstream.git"
    if [[ ! -d "$CLONE" ]]; then
        git clone --bare "$GIT_URL" "$CLONE"
    elif ! git --git-dir="$CLONE" cat-file -e "${REV:-$DEFAULT_REV}^{commit}" 2>/dev/null; then
        git --git-dir="$CLONE" fetch "$GIT_URL" '+refs/heads/*:refs/heads/*'
    fi
    from_git "$CLONE"
fi

# ---- 3. The two changes ----------------------------------------------------------------------------------
find "$STAGE" -type f \( -name '*.cpp' -o -name '*.cc' -o -name '*.h' -o -name '*.hpp' \) \
    -exec sed -i -E -f "$SED_SCRIPT" {} +
sed -i 's/-std=c++11/-std=c++17/' "$STAGE/camera_models/CMakeLists.txt" "$STAGE/vins_estimator/CMakeLists.txt"
left=$(grep -rnE '\bCV_(LOAD_IMAGE_[A-Z]+|AA|[A-Z]+2[A-Z]+|CALIB_CB_[A-Z_]+|ADAPTIVE_THRESH_[A-Z_]+|THRESH_[A-Z_]+|RETR_[A-Z]+|CHAIN_APPROX_[A-Z]+|SHAPE_[A-Z]+|TERMCRIT_[A-Z]+)\b' "$STAGE" || true)
[[ -z "$left" ]] || die "OpenCV C constants left after the patch (upstream changed?):"$'\n'"$left"
if [[ "$YAW_GAUGE" == 1 ]]; then
    patch -d "$STAGE" -p1 --forward --quiet < "$YAW_PATCH" \
        || die "$YAW_PATCH does not apply to this source (upstream changed?)"
    echo "build_vins_fusion: applied $(basename "$YAW_PATCH")"
fi

# Replace the workspace's copy only when it differs, so that an unchanged tree rebuilds nothing.
DEST="$WS/src/VINS-Fusion"
if [[ -d "$DEST" ]] && diff -rq "$STAGE" "$DEST" >/dev/null 2>&1; then
    echo "build_vins_fusion: $DEST is up to date"
else
    rm -rf "$DEST"
    mkdir -p "$DEST"
    mv "$STAGE/camera_models" "$STAGE/vins_estimator" "$DEST/"
    echo "build_vins_fusion: wrote $DEST"
fi

# ---- 4. Build vins_node (and the camera_models library it links) -----------------------------------------
cd "$WS"
# Debian's catkin runs on Debian's python3 (catkin_pkg and friends are python3-* packages): keep a venv,
# pyenv or conda python of the caller's out of the build.
unset PYTHONPATH PYTHONHOME VIRTUAL_ENV CONDA_PREFIX
export PATH=/usr/sbin:/usr/bin:/sbin:/bin
# catkin_make passes extra arguments to make: the target vins_node builds its libraries and nothing else.
catkin_make -DCMAKE_BUILD_TYPE=Release -DPYTHON_EXECUTABLE=/usr/bin/python3 "-j$JOBS" vins_node

NODE="$WS/devel/lib/vins/vins_node"
[[ -x "$NODE" ]] || die "the build finished but $NODE is missing"
echo
echo "vins_node: $NODE"
echo "workspace: $WS   (source $WS/devel/setup.bash, then: rosrun vins vins_node CONFIG)"
