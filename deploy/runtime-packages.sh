#!/usr/bin/env bash
# Prints the Debian packages that hold the shared libraries a binary links directly (its ELF
# NEEDED entries), one per line, sorted: what a runtime image or machine must install to run it
# without the -dev packages (apt pulls their own dependencies). The C library and the other
# essential packages are left out. Fails if a library is not found or not from a package.
#   deploy/runtime-packages.sh build/server/vasld
set -euo pipefail
bin="${1:?usage: runtime-packages.sh BINARY}"
command -v objdump > /dev/null || { echo "runtime-packages: objdump missing (binutils)" >&2; exit 1; }

declare -A paths=()
while read -r lib _ path _; do
  [ "$path" = "not" ] && { echo "runtime-packages: $lib: not found" >&2; exit 1; }
  [ -n "$path" ] && paths["$lib"]="$path"
done < <(ldd "$bin" | awk '$2 == "=>" {print $1, $2, $3}' | sed 's/ => / x /')

status=0
out=()
for lib in $(objdump -p "$bin" | awk '$1 == "NEEDED" {print $2}'); do
  case "$lib" in ld-linux*|libc.so.*|libm.so.*|libgcc_s.so.*) continue ;; esac  # libc6, libgcc-s1
  path="${paths[$lib]:-}"
  [ -n "$path" ] || { echo "runtime-packages: $lib: not resolved by ldd" >&2; status=1; continue; }
  pkg=""
  # dpkg records some libraries under /lib, others under /usr/lib (merged /usr): try both.
  for p in "$path" "$(readlink -f "$path")" "/usr${path#/usr}" "${path#/usr}"; do
    pkg="$(dpkg-query -S "$p" 2> /dev/null | head -n1 | cut -d: -f1)" && [ -n "$pkg" ] && break
  done
  if [ -z "$pkg" ]; then
    echo "runtime-packages: $lib ($path) belongs to no package" >&2
    status=1
    continue
  fi
  [ "$(dpkg-query -W -f='${Essential}' "$pkg" 2> /dev/null)" = "yes" ] && continue
  out+=("$pkg")
done
[ "${#out[@]}" -eq 0 ] || printf '%s\n' "${out[@]}" | sort -u
exit "$status"
