"""mocapskel: template-free skeletons from raw optical motion-capture markers."""
import os as _os

# One BLAS thread per process unless the user chose otherwise. The solvers'
# matrices are small and many; BLAS threads gain little on them and, beside
# any other busy process (a batch's other workers, say), spin against each
# other and run several times slower. Batches parallelise over takes instead.
# These variables act only where numpy is first imported after this; where it was
# imported before (``import numpy`` then ``import mocapskel``: twice the time of a fit
# measured on two cores), the pipeline's entry points set the same limit at run time
# (see mocapskel.blas.one_blas_thread).
# A process started from one that imported mocapskel inherits the variables it set;
# MOCAPSKEL_BLAS_DEFAULT says they are ours, not the user's.
_BLAS_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
BLAS_THREADS_CHOSEN = (any(_v in _os.environ for _v in _BLAS_VARS)
                       and _os.environ.get("MOCAPSKEL_BLAS_DEFAULT") != "1")  # the user's choice is kept
if not BLAS_THREADS_CHOSEN:
    for _v in _BLAS_VARS:
        _os.environ.setdefault(_v, "1")
    _os.environ["MOCAPSKEL_BLAS_DEFAULT"] = "1"
    del _v

__version__ = "0.1.0"
