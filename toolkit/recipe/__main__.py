"""``python -m toolkit.recipe run|validate|list``."""

import os
import signal

# OpenMP threads that spin while waiting steal the cores from each other on a busy
# 2-core laptop (measured 10x slower splat training); must be set before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# OpenBLAS's idle threads spin for 2^28 cycles (~0.1 s) after every operation it splits
# over the cores; 2^4 puts them to sleep at once. The fuse stage's evaluation takes three
# dot products of whole images per frame, and their threads' spinning ran on into the
# fusion's timed work: 11 of the paper benchmark's fuse_net 36.5 s of CPU time (24.9 s
# with this; the same outputs and metrics, since the same operations are still split).
# OpenBLAS reads it when numpy loads it: set before anything imports numpy.
os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "4")

from toolkit.recipe.cli import INTERRUPTED, main  # noqa: E402

if __name__ == "__main__":
    code = main()
    if code == INTERRUPTED:
        # The run's state is saved by now. Python then joins the worker threads still
        # winding down (prefetch, onnxruntime); a second Ctrl-C there printed an
        # "Exception ignored in atexit callback" traceback and waited on: with the default
        # action it ends the process at once, as users expect of a second Ctrl-C.
        signal.signal(signal.SIGINT, signal.SIG_DFL)
    raise SystemExit(code)
