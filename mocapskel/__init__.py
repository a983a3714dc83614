"""mocapskel: template-free skeletons from raw optical motion-capture markers."""
import os as _os

# One BLAS thread per process unless the user chose otherwise. The solvers'
# matrices are small and many; BLAS threads gain little on them and, beside
# any other busy process (a batch's other workers, say), spin against each
# other and run several times slower. Batches parallelise over takes instead.
# (Only effective when numpy is first imported after this.)
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
del _var

__version__ = "0.1.0"
