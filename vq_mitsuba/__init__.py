"""vq-mitsuba: neural reflectance decomposition and material editing (VQ-NeRF) on Mitsuba 3."""

__version__ = "0.1.0"

import os as _os

# OpenMP threads (torch's CPU kernels) sleep instead of spinning while they wait: with another
# busy process on the machine, spinning threads take its cores and slow both down many times over.
# But first they spin GOMP_SPINCOUNT turns (microseconds): a step of many short parallel regions
# (NeuS's, eager or compiled) would otherwise wake a sleeping thread for each and run on 1.4
# cores, 1.4x slower eagerly and 3x compiled (benchmarks/results/compiled/).
# Only effective when set before torch is first imported; a value already in the environment wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
_os.environ.setdefault("GOMP_SPINCOUNT", "1000")
