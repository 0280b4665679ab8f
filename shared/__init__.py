"""twohr common library: the contracts every service shares.

Modules: ``errors`` (user-facing errors), ``geometry`` (SE(3), quaternions, Umeyama),
``trajectory`` (TUM trajectory I/O), ``evaluation`` (ATE/RPE as in the TUM tools and evo),
``plots``, ``dataset`` (TUM-layout RGB-D sequences), ``models`` (verified model registry),
``config`` (typed pipeline configuration) and ``synthetic`` (exact synthetic sequences).
"""

__version__ = "0.1.0"
