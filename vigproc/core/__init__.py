"""The numeric core: pure functions over arrays (model, statistics, priors, estimators, correction, Numba kernels)."""
