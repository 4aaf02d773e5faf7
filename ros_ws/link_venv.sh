#!/bin/sh
# Put `sep` on the PATH of an activated venv, running the colcon install space (the same copy
# of the packages as the ROS executables; no second copy in the venv).  Called by `make build`
# and `make clean`:
#
#   link_venv.sh VENV INSTALL PKG...   write VENV/bin/sep and <VENV site-packages>/sep_ros_ws.pth
#   link_venv.sh --remove VENV         remove both (only files this script wrote)
#
# sep_ros_ws.pth lists <INSTALL>/<PKG>/lib/pythonX.Y/site-packages of each package, so that the
# venv's python imports the installed packages.  VENV/bin/sep exports AMENT_PREFIX_PATH and
# PYTHONPATH as INSTALL/setup.sh does (`sep demo` resolves the node executables through the
# ament index, like `ros2 run`) and execs INSTALL/sep_control/lib/sep_control/sep.
set -eu

MARK='written by ros_ws/link_venv.sh of sep'
PTH=sep_ros_ws.pth

die() { echo "link_venv.sh: error: $*" >&2; exit 2; }

if [ "${1:-}" = --remove ]; then
  [ $# -eq 2 ] || die "usage: link_venv.sh --remove VENV"
  venv=$2
  # only sep's launcher: a console script of a pip-installed sep_control stays
  if [ -f "$venv/bin/sep" ] && grep -qF "$MARK" "$venv/bin/sep"; then rm -f "$venv/bin/sep"; fi
  for site in "$venv"/lib/python3*/site-packages; do
    if [ -f "$site/$PTH" ]; then rm -f "$site/$PTH"; fi
  done
  exit 0
fi

[ $# -ge 3 ] || die "usage: link_venv.sh VENV INSTALL PKG..."
venv=$1 install=$2
shift 2
python="$venv/bin/python"
[ -x "$python" ] || die "$python not found: create the venv first (make venv)"
exe="$install/sep_control/lib/sep_control/sep"
[ -x "$exe" ] || die "$exe not found: build the workspace first (make build)"
case "$install" in *"'"*) die "the install path must not contain a single quote: $install" ;; esac
if [ -e "$venv/bin/sep" ] && ! grep -qF "$MARK" "$venv/bin/sep"; then
  die "$venv/bin/sep exists and is not sep's launcher (a pip-installed sep_control?): remove it"
fi

pyver=$("$python" -c 'import sys; print("python%d.%d" % sys.version_info[:2])')
site=$("$python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')

# PKG... in dependency order; install/setup.sh puts the last package first (dependents before
# their dependencies) on both paths
pypath='' ament=''
for pkg in "$@"; do
  pypath="$install/$pkg/lib/$pyver/site-packages${pypath:+:}$pypath"
  ament="$install/$pkg${ament:+:}$ament"
done

{
  echo "# $MARK for $install (removed by make clean)"
  echo "$pypath" | tr ':' '\n'
} > "$site/$PTH"

tmp="$venv/bin/.sep.tmp.$$"
cat > "$tmp" <<EOF
#!/bin/sh
# sep from the colcon install $install ($MARK;
# removed by make clean): the environment install/setup.sh gives the ROS executables, then the
# installed console script.
exe='$exe'
if [ ! -x "\$exe" ]; then
  echo "sep: \$exe not found: run make build in the sep checkout" >&2
  exit 127
fi
AMENT_PREFIX_PATH='$ament'\${AMENT_PREFIX_PATH:+:\$AMENT_PREFIX_PATH}
PYTHONPATH='$pypath'\${PYTHONPATH:+:\$PYTHONPATH}
export AMENT_PREFIX_PATH PYTHONPATH
exec "\$exe" "\$@"
EOF
chmod +x "$tmp"
mv -f "$tmp" "$venv/bin/sep"
