#!/usr/bin/env bash
# Builds the ROS 2 interface package tf2_msgs (tools/tf2_msgs: msg/TFMessage.msg only) and
# installs it into the venv, next to the ROS 2 Jazzy wheels, laid out as those wheels lay out
# geometry_msgs:
#   .venv/lib/libtf2_msgs__rosidl_{generator_c,typesupport_c,typesupport_fastrtps_c,
#            typesupport_introspection_c,generator_py}.so
#   .venv/lib/python3.X/site-packages/tf2_msgs/  (msg/ modules + tf2_msgs_s__<ts>.so)
#   .venv/include/tf2_msgs/tf2_msgs/msg/...      (C headers)
#   .venv/share/tf2_msgs/                        (package.xml, msg/TFMessage.{msg,idl,json})
#   .venv/share/ament_index/resource_index/{packages,rosidl_interfaces}/tf2_msgs
# tf2_msgs is not on PyPI, and the wheels carry no ament_cmake, so instead of
# rosidl_generate_interfaces() the pip-installed rosidl generators are called directly
# (tools/rosidl_generate.py) and their output compiled with gcc/g++.
#
# Usage: tools/build_tf2_msgs.sh [VENV]   (default: .venv of this repository)
# Idempotent: does nothing when the installed build matches the current sources
# (stamp VENV/.tf2_msgs-installed holds their checksum) and `import tf2_msgs.msg` works.
# Needs gcc, g++ and the venv's Python headers (pyenv/python.org builds ship them).
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
repo=$(dirname "$here")
venv=$(cd "${1:-$repo/.venv}" && pwd)
py=$venv/bin/python
src=$here/tf2_msgs
pkg=tf2_msgs
stamp=$venv/.tf2_msgs-installed

# Everything that decides the result: sources, this script, the generator driver, and the
# versions of the ROS wheels it builds against.
sum=$(
  {
    cat "$0" "$here/rosidl_generate.py" "$src/package.xml" "$src"/msg/*.msg
    "$py" -m pip list --format=freeze 2>/dev/null | grep -i '^ros-' || true
  } | sha256sum | cut -d' ' -f1
)
if [[ -f $stamp && $(cat "$stamp") == "$sum" ]] &&
  "$py" -c "from tf2_msgs.msg import TFMessage; TFMessage.__class__.__import_type_support__(); \
assert TFMessage._TYPE_SUPPORT is not None" 2>/dev/null; then
  echo "tf2_msgs: up to date in $venv"
  exit 0
fi

for tool in gcc g++; do
  command -v "$tool" > /dev/null || { echo "tf2_msgs: $tool is needed" >&2; exit 1; }
done

site=$("$py" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
py_inc=$("$py" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
np_inc=$("$py" -c 'import numpy; print(numpy.get_include())')
ext_suffix=.so # what the wheels use for tf2_msgs_s__<ts>.so (import_type_support finds it)
[[ -f $py_inc/Python.h ]] || { echo "tf2_msgs: no Python.h in $py_inc" >&2; exit 1; }

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
gen=$work/gen
start=$SECONDS

echo "tf2_msgs: generating sources"
AMENT_PREFIX_PATH=$venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH} \
  "$py" "$here/rosidl_generate.py" "$pkg" "$src" "$venv/share" "$gen" 2> "$work/generate.log" ||
  { cat "$work/generate.log" >&2; exit 1; }

# Include paths: every installed ROS package keeps its headers in include/<pkg>/<pkg>/...
incs=(-I"$gen/generator_c" -I"$gen/typesupport_fastrtps_c" -I"$gen/typesupport_introspection_c"
  -I"$venv/include")
for d in "$venv"/include/*/; do incs+=(-I"${d%/}"); done
common=(-O2 -fPIC -w -L"$venv/lib" -Wl,-rpath,'$ORIGIN' -L"$work/lib")
mkdir -p "$work/lib"
lib=$work/lib

echo "tf2_msgs: compiling"
# 1. C structs and functions.
gcc -shared "${common[@]}" "${incs[@]}" -DROSIDL_GENERATOR_C_BUILDING_DLL_$pkg \
  "$gen"/generator_c/$pkg/msg/detail/*.c -o "$lib/lib${pkg}__rosidl_generator_c.so" \
  -lgeometry_msgs__rosidl_generator_c -lstd_msgs__rosidl_generator_c \
  -lbuiltin_interfaces__rosidl_generator_c -lrosidl_runtime_c -lrcutils
# 2-4. The type supports; rosidl_typesupport_c finds the other two at run time.
gcc -shared "${common[@]}" "${incs[@]}" \
  -DROSIDL_TYPESUPPORT_INTROSPECTION_C_BUILDING_DLL_$pkg \
  "$gen"/typesupport_introspection_c/$pkg/msg/detail/*.c \
  -o "$lib/lib${pkg}__rosidl_typesupport_introspection_c.so" \
  -l${pkg}__rosidl_generator_c -lgeometry_msgs__rosidl_typesupport_introspection_c \
  -lrosidl_runtime_c -lrcutils
g++ -std=c++17 -shared "${common[@]}" "${incs[@]}" \
  -DROSIDL_TYPESUPPORT_FASTRTPS_C_BUILDING_DLL_$pkg \
  "$gen"/typesupport_fastrtps_c/$pkg/msg/detail/*.cpp \
  -o "$lib/lib${pkg}__rosidl_typesupport_fastrtps_c.so" \
  -l${pkg}__rosidl_generator_c -lgeometry_msgs__rosidl_typesupport_fastrtps_c \
  -lgeometry_msgs__rosidl_generator_c -lrosidl_typesupport_fastrtps_c \
  -lrosidl_typesupport_fastrtps_cpp -lrosidl_runtime_c -lfastcdr -lrmw -lrcutils
g++ -std=c++17 -shared "${common[@]}" "${incs[@]}" -DROSIDL_TYPESUPPORT_C_BUILDING_DLL_$pkg \
  "$gen"/typesupport_c/$pkg/msg/*.cpp -o "$lib/lib${pkg}__rosidl_typesupport_c.so" \
  -l${pkg}__rosidl_generator_c -lrosidl_typesupport_c -lrosidl_runtime_c -lrcpputils -lrcutils
# 5. Python <-> C conversion functions, then one extension module per type support.
gcc -shared "${common[@]}" "${incs[@]}" -I"$py_inc" -I"$np_inc" \
  "$gen"/generator_py/$pkg/msg/*_s.c -o "$lib/lib${pkg}__rosidl_generator_py.so" \
  -l${pkg}__rosidl_generator_c -l${pkg}__rosidl_typesupport_c \
  -lgeometry_msgs__rosidl_generator_py -lgeometry_msgs__rosidl_generator_c \
  -lrosidl_runtime_c -lrcutils
mkdir -p "$work/py"
for ts in rosidl_typesupport_c rosidl_typesupport_fastrtps_c rosidl_typesupport_introspection_c; do
  gcc -shared "${common[@]}" "${incs[@]}" -I"$py_inc" -I"$np_inc" \
    -Wl,-rpath,'$ORIGIN/../../..' \
    "$gen/generator_py/$pkg/_${pkg}_s.ep.$ts.c" -o "$work/py/${pkg}_s__$ts$ext_suffix" \
    -l${pkg}__rosidl_generator_py -l${pkg}__$ts -l${pkg}__rosidl_generator_c \
    -lrosidl_runtime_c -lrmw -lrcutils
done

echo "tf2_msgs: installing into $venv"
rm -rf "${site:?}/$pkg" "$venv/include/$pkg" "$venv/share/$pkg"
rm -f "$venv"/lib/lib${pkg}__*.so "$stamp"
# Python package: generated modules + extension modules.
mkdir -p "$site/$pkg"
cp -r "$gen/generator_py/$pkg/msg" "$site/$pkg/msg"
rm -f "$site/$pkg"/msg/*.c
cp "$work"/py/*.so "$site/$pkg/"
: > "$site/$pkg/__init__.py"
install -m 755 "$lib"/*.so "$venv/lib/"
# Headers, interface definitions and the ament index entries (for `ros2 interface`,
# rosidl_get_typesupport lookups and downstream generators).
mkdir -p "$venv/include/$pkg/$pkg/msg/detail" "$venv/share/$pkg/msg"
for g in generator_c typesupport_fastrtps_c typesupport_introspection_c; do
  (cd "$gen/$g/$pkg" && find . -name '*.h' -exec cp --parents {} "$venv/include/$pkg/$pkg/" \;)
done
cp "$src/package.xml" "$venv/share/$pkg/"
cp "$src"/msg/*.msg "$gen"/idl/msg/*.idl "$gen"/type_description/msg/*.json "$venv/share/$pkg/msg/"
index=$venv/share/ament_index/resource_index
mkdir -p "$index/packages" "$index/rosidl_interfaces"
: > "$index/packages/$pkg"
(cd "$src" && for m in msg/*.msg; do echo "$m"; echo "${m%.msg}.idl"; done) \
  > "$index/rosidl_interfaces/$pkg"

"$py" -c "from tf2_msgs.msg import TFMessage; TFMessage.__class__.__import_type_support__(); \
assert TFMessage._TYPE_SUPPORT is not None, 'tf2_msgs type support did not load'"
echo "$sum" > "$stamp"
echo "tf2_msgs: built and installed in $((SECONDS - start)) s"
