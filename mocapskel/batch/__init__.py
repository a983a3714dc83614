"""Many takes at once: locally in worker processes or on a Dask cluster.

    run_batch(inputs, outdir, options)      fit every take, write <take>.bvh, <take>.json
                                            and summary.csv, identify subjects

Work is split so that it runs the same on one machine and on a cluster:

- the *workers* run :func:`~mocapskel.batch.worker.fit_take`: they read the input take from its path
  (so on a cluster the inputs must be at the same path on every worker, e.g. a
  shared file system), use their own artifact cache, and send back the BVH
  text and the report;
- the *client* (this process) expands the inputs, skips takes whose outputs are
  up to date, writes every output atomically (:mod:`mocapskel.io.atomic`) and
  the summary. Outputs never need to be visible to the workers, and an
  interrupted batch leaves no partial file behind.

Subject identification (Kirk et al. 2005, §5: skeletons of one person have
the same proportions) compares the joint-to-joint bone lengths of fitted
skeletons that share a topology; see :func:`~mocapskel.batch.proportions.proportion_distance`,
:func:`~mocapskel.batch.proportions.compare_reports` and :func:`~mocapskel.batch.clustering.identify_subjects`.
"""
from __future__ import annotations

from .proportions import SAME_SUBJECT_PCT, Bones, Comparison, compare_bones
from .run import run_batch
from .tasks import BatchOptions, Take, TakeResult
from .worker import warm_up

__all__ = ["SAME_SUBJECT_PCT", "BatchOptions", "Bones", "Comparison", "Take", "TakeResult", "compare_bones", "run_batch",
           "warm_up"]
