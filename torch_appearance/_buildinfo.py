"""Build fingerprint shared by setup.py (at build time) and the import-time check (no torch import here)."""
import hashlib
import os

_SOURCE_SUFFIXES = (".cpp", ".h", ".hpp", ".cu", ".cuh")
#: folders of csrc/ that the extension does not compile: the CUDA glue, compiled at run time by NVRTC and cached
#: under its own key (torch_appearance/render/cuda_kernels.py), so that a change there asks for no rebuild
_NOT_BUILT = ("cuda",)


def source_hash(csrc_dir):
    """SHA-256 (first 16 hex digits) over the relative paths and contents of the C++ sources in ``csrc_dir`` that
    the extension compiles (all but the folders of ``_NOT_BUILT``)."""
    digest = hashlib.sha256()
    for root, _, files in sorted(os.walk(csrc_dir)):
        if os.path.relpath(root, csrc_dir).split(os.sep)[0] in _NOT_BUILT:
            continue
        for name in sorted(files):
            if name.endswith(_SOURCE_SUFFIXES):
                path = os.path.join(root, name)
                digest.update(os.path.relpath(path, csrc_dir).replace(os.sep, "/").encode())
                with open(path, "rb") as handle:
                    digest.update(handle.read())
    return digest.hexdigest()[:16]
