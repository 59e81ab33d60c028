#!/usr/bin/env bash
# Install the toolkit and its dependencies into the active Python environment.
# Open3D's wheel links against libusb-1.0, which slim Debian/Ubuntu images lack;
# we install it when we can (root or sudo with apt) and say so when we cannot.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"

if ! ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so.0"; then
  if command -v apt-get >/dev/null && [ "$(id -u)" = "0" ]; then
    apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null
  elif command -v apt-get >/dev/null && command -v sudo >/dev/null; then
    sudo apt-get update -qq && sudo apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    echo "warning: libusb-1.0 not found; 'import open3d' will fail until it is installed" >&2
  fi
fi

# constraints.txt pins torch 2.13.0. On Linux, PyPI's torch is the CUDA build (several GB
# of nvidia-* wheels), so the CPU build comes from PyTorch's own index first - unless a
# torch is installed already (a CUDA one you chose stays) or a wheel of the pinned version
# is at hand without any index (a local wheel folder in pip's configuration).
TORCH_PIN="$(grep -E '^torch==' constraints.txt)"
if ! python -c "import torch" >/dev/null 2>&1 \
    && ! python -m pip install --dry-run --no-index --no-deps -q "$TORCH_PIN" >/dev/null 2>&1; then
  python -m pip install -c constraints.txt "$TORCH_PIN" \
    --index-url "${TORCH_INDEX_URL:-https://download.pytorch.org/whl/cpu}"
fi
python -m pip install --upgrade-strategy only-if-needed -c constraints.txt -e ".[dev,export]"
python -c "import toolkit, open3d, torch, cv2; print('toolkit', toolkit.__version__, '| torch', torch.__version__, '| open3d', open3d.__version__)"
