"""The names of vigproc's estimators (a light module: the command line's parser and
the settings check need the names, not the estimators)."""

#: Methods :func:`vigproc.core.estimate.estimate` accepts. "default": the lens-family fit,
#: or an off-centre fit for a frame whose centre is clearly off (a crop).
METHODS = ("default", "robust", "real-lens", "flat-field", "lens-family", "lyu2010", "lyu2010-rand", "ga")
#: The methods that are vigproc's robust Kang-Weiss estimator ("default" when given
#: RobustSettings).
ROBUST_METHODS = ("default", "robust", "real-lens", "flat-field")
#: The methods whose frames give evidence for profile pooling, all through the robust
#: estimator (pooling assumes photographs of scenes: :mod:`vigproc.core.pooling` subtracts a
#: scene's mean fall-off).
EVIDENCE_METHODS = ("default", "robust", "real-lens")
