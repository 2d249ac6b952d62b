#!/usr/bin/env bash
# What psdr needs on the GPU machine beyond the shared bundle (run after `bash ../shared/gpu/bundle.sh`,
# in the checkout's root; see docs/testing.md, "The suite on a GPU"):
#   - the xatlas wheel (psdr imports it at start-up; 0.26 MB) in .gpu/whl/, which check.sh installs;
#   - .gpu/stub/cv2: OpenCV's and pycolmap's wheels (56 and 38 MB) do not fit the 64 MiB carry, so a
#     stand-in module that raises ImportError on use lets psdr start; the photograph modules' tests
#     are left out there;
#   - .gpu/psdr-check.sh: check.sh with the stub on PYTHONPATH and those test modules ignored.
# Then, on the device: carry [".gpu"], command `bash .gpu/psdr-check.sh`, timeout_s 570.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
[ -f .gpu/check.sh ] || { echo "no .gpu/check.sh: run 'bash ../shared/gpu/bundle.sh' first" >&2; exit 1; }

python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 -d .gpu/whl "xatlas==0.0.11"

mkdir -p .gpu/stub/cv2
cat > .gpu/stub/cv2/__init__.py <<'EOF'
"""Stand-in for OpenCV on the GPU machine (its wheel does not fit the carry): importable, unusable."""


def __getattr__(name):
    raise ImportError(f"cv2.{name}: OpenCV is not installed on the GPU machine (scripts/gpu-extras.sh)")
EOF

cat > .gpu/psdr-check.sh <<'EOF'
#!/usr/bin/env bash
# check.sh for psdr: the cv2 stand-in on the path (unless the machine has OpenCV), the photograph tests left out.
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
if ! python3 -c "import cv2" 2>/dev/null; then
    export PYTHONPATH="$here/stub${PYTHONPATH:+:$PYTHONPATH}"
    : "${TEST_ARGS:=-q -n 14 --dist loadgroup --maxfail=30 --durations=15 -p no:cacheprovider -rf tests --ignore=tests/test_datasets.py --ignore=tests/test_photographs.py --ignore=tests/test_unknown_light.py}"
    export TEST_ARGS
    echo "no OpenCV here: cv2 stand-in on PYTHONPATH, photograph tests left out"
fi
exec bash "$here/check.sh" "$@"
EOF
du -sh .gpu
echo "ready: device run with carry [\".gpu\"], command 'bash .gpu/psdr-check.sh', timeout_s 570"
