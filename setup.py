"""Thin build script: only the C++ extension ``torch_appearance._C`` (metadata lives in setup.cfg).

Build ahead of time, without build isolation so the extension links against the torch that is installed::

    pip install -e . --no-build-isolation      # or: make build

The build records a hash of the csrc/ sources and the torch version; loading the extension (on first use of the
tracer: ``torch_appearance.render_scene``, ``from torch_appearance import _C``) compares them with the checkout and
tells you to rebuild when they differ (see torch_appearance/_ext.py).
"""
import glob
import os
import sys

from setuptools import setup

try:
    import torch
    from torch.utils.cpp_extension import BuildExtension, CppExtension
except ImportError:  # pragma: no cover - message for people who forget the order
    sys.exit("torch_appearance: install torch first, then build without isolation: "
             "pip install torch && pip install -e . --no-build-isolation  (or simply: make build)")

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "torch_appearance"))
from _buildinfo import source_hash  # noqa: E402  (plain-python helper, no torch import)

# The tracing core (csrc/core/*.h) is plain C++17 and host/device clean; the glue follows the C++ standard torch itself requires
# (C++20 since torch 2.10), which CppExtension selects.
sources = sorted(glob.glob(os.path.join("csrc", "**", "*.cpp"), recursive=True))
cxx_flags = ["-O3", "-fopenmp", "-ffp-contract=off", "-Wall", "-Wno-unused-function"]

# The source hash and torch version go into a generated header that only bindings.cpp includes (not onto every
# command line, where a changed hash would make ninja recompile every file after any edit); it is rewritten only
# when its text changes.
GENERATED = os.path.join(HERE, "build", "generated")
os.makedirs(GENERATED, exist_ok=True)
_info = (f'#define TA_SOURCE_HASH "{source_hash(os.path.join(HERE, "csrc"))}"\n'
         f'#define TA_TORCH_VERSION "{torch.__version__}"\n')
_header = os.path.join(GENERATED, "ta_buildinfo.h")
if not os.path.exists(_header) or open(_header).read() != _info:
    with open(_header + ".tmp", "w") as fh:
        fh.write(_info)
    os.replace(_header + ".tmp", _header)

# TA_SKIP_EXT=1 registers the editable install without compiling (the Makefile then builds in place once).
ext_modules = [] if os.environ.get("TA_SKIP_EXT") == "1" else [
    CppExtension("torch_appearance._C", sources,
                 include_dirs=[os.path.join(HERE, "csrc"), GENERATED],
                 extra_compile_args={"cxx": cxx_flags},
                 extra_link_args=["-fopenmp"])]

setup(
    ext_modules=ext_modules,
    cmdclass={"build_ext": BuildExtension.with_options(use_ninja=True)},
)
