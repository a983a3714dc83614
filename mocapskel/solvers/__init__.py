"""Numerical kernels. They know no pipeline and do no I/O."""
