#!/usr/bin/env bash
# The runtime package list (scripts/setup-runtime-deps.sh, the runtime stage
# of deploy/docker/Dockerfile.cpu) is complete and real:
#  1. every name is a Debian package (apt-cache show, or installed here when
#     this machine has no apt lists);
#  2. every shared library that the built binaries link directly is owned by
#     one of those packages.
# Usage: runtime_deps_test.sh REPO_ROOT BINARY...
set -euo pipefail

root=$1
shift
mapfile -t packages < <("$root/scripts/setup-runtime-deps.sh" --list)
[[ ${#packages[@]} -gt 0 ]] || { echo "FAIL: --list printed no packages"; exit 1; }

failed=0
for p in "${packages[@]}"; do
  if apt-cache show --no-all-versions "$p" >/dev/null 2>&1; then
    continue
  fi
  status=$(dpkg-query -W -f='${Status}' "$p" 2>/dev/null || true)
  if [[ "$status" != "install ok installed" ]]; then
    echo "FAIL: '$p' is neither known to apt-cache nor installed"
    failed=1
  fi
done

# Direct libraries (NEEDED) of every binary, resolved by the loader.
declare -A lib_path=()   # path -> "binary: lib" (for messages)
for binary in "$@"; do
  [[ -x "$binary" ]] || { echo "FAIL: $binary is not an executable"; failed=1; continue; }
  ldd_out=$(ldd "$binary")
  while read -r lib; do
    path=$(awk -v l="$lib" '$1 == l && $2 == "=>" {print $3; exit}' <<<"$ldd_out")
    if [[ -z "$path" || "$path" == "not" ]]; then
      echo "FAIL: $(basename "$binary") needs $lib, which the loader does not find"
      failed=1
      continue
    fi
    lib_path[$path]="$(basename "$binary"): $lib"
  done < <(objdump -p "$binary" | awk '/^ *NEEDED/ {print $2}')
done

# One dpkg-query for all of them (it scans every file list once). dpkg
# records a file under the path its package ships it at; with merged /usr the
# loader may report /lib/... for /usr/lib/... (or the reverse), so each path
# is asked for in its forms.
declare -A form_of=()    # queried form -> loader path
for path in "${!lib_path[@]}"; do
  real=$(readlink -f "$path")
  for form in "$path" "$real" "/usr$path" "/usr$real" "${path#/usr}" "${real#/usr}"; do
    form_of[$form]=$path
  done
done
declare -A owner=()      # loader path -> package
if [[ ${#form_of[@]} -gt 0 ]]; then
  while IFS= read -r line; do
    pkg=${line%%: *}
    file=${line#*: }
    pkg=${pkg%%,*}
    pkg=${pkg%%:*}
    [[ -n "${form_of[$file]:-}" ]] && owner[${form_of[$file]}]=$pkg
  done < <(dpkg-query -S "${!form_of[@]}" 2>/dev/null || true)
fi

for path in "${!lib_path[@]}"; do
  pkg=${owner[$path]:-}
  if [[ -z "$pkg" ]]; then
    echo "FAIL: ${lib_path[$path]} ($path) is owned by no package"
    failed=1
    continue
  fi
  found=0
  for p in "${packages[@]}"; do
    [[ "$p" == "$pkg" ]] && found=1
  done
  if [[ $found -eq 0 ]]; then
    echo "FAIL: ${lib_path[$path]} comes from package '$pkg';" \
         "add it to scripts/setup-runtime-deps.sh"
    failed=1
  fi
done

if [[ $failed -ne 0 ]]; then exit 1; fi
echo "OK: ${#packages[@]} runtime packages cover the ${#lib_path[@]} libraries that $# binaries link"
