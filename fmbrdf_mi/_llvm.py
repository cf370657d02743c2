"""Guard against an LLVM that Dr.Jit 1.5 cannot use.

Dr.Jit's LLVM backend emits ``llvm.maximum``/``llvm.minimum`` intrinsics that
the x86 instruction selector of LLVM 15 and older cannot lower: the process
aborts (``LLVM ERROR: Cannot select ... fmaximum``) on the first render.  We
detect that before any kernel is compiled and raise a Python error that says
how to fix it.
"""
import glob
import os
import re

#: Oldest libLLVM major version with which Dr.Jit 1.5 was seen to work.
MIN_LLVM_MAJOR = 16

_FIX = (
    "Install a newer LLVM, e.g. on Debian/Ubuntu `apt-get install -y libllvm19`, "
    "or point Dr.Jit at one with DRJIT_LIBLLVM_PATH=/path/to/libLLVM.so.19."
)


class LLVMTooOldError(RuntimeError):
    """Raised when Dr.Jit's LLVM backend would crash on this machine."""


def pin_newest_llvm():
    """Point Dr.Jit at the newest system libLLVM unless the user chose one.

    Only has an effect when called before Dr.Jit initialises its LLVM backend.
    """
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return
    found = []
    for path in glob.glob("/usr/lib/*/libLLVM*.so*") + glob.glob("/usr/lib/llvm-*/lib/libLLVM*.so*"):
        m = re.search(r"libLLVM(?:-|\.so\.)(\d+)", os.path.basename(path))
        if m:
            found.append((int(m.group(1)), path))
    if found and max(found)[0] >= MIN_LLVM_MAJOR:
        os.environ["DRJIT_LIBLLVM_PATH"] = max(found)[1]


def check_llvm():
    """Raise :class:`LLVMTooOldError` if Dr.Jit's LLVM backend is unusable."""
    import drjit as dr

    try:
        version = dr.detail.llvm_version()
    except Exception:  # no LLVM at all: only CUDA/scalar variants can run
        return None
    if version is None or version[0] == 0:
        return None
    if version[0] < MIN_LLVM_MAJOR:
        raise LLVMTooOldError(
            f"Dr.Jit is using libLLVM {'.'.join(map(str, version))}, which crashes "
            f"Dr.Jit 1.5 on the first render (needs LLVM >= {MIN_LLVM_MAJOR}). {_FIX}"
        )
    return version
