#!/usr/bin/env bash
# Make sure a libLLVM >= 16 is present for Dr.Jit's LLVM backend (LLVM 15 aborts with
# "Cannot select: fminimum"). Installs Debian's libllvm19 when running as root.
set -eu
have_llvm() {
    { ldconfig -p 2>/dev/null | grep -oE 'libLLVM(-|\.so\.)[0-9]+' ;
      ls /usr/lib/*/libLLVM* /usr/lib/llvm-*/lib/libLLVM* 2>/dev/null | grep -oE 'libLLVM(-|\.so\.)[0-9]+' ; } |
        grep -oE '[0-9]+$' | awk '$1 >= 16 {found=1} END {exit !found}'
}
if have_llvm; then exit 0; fi
if [ -n "${DRJIT_LIBLLVM_PATH:-}" ] && [ -e "$DRJIT_LIBLLVM_PATH" ]; then exit 0; fi
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "psdr: installing libllvm19 (Dr.Jit needs LLVM >= 16)"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null
    have_llvm && exit 0
fi
echo "psdr: no libLLVM >= 16 found; install one, e.g. 'sudo apt-get install libllvm19'" >&2
exit 1
