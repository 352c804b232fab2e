"""vq-mitsuba: neural reflectance decomposition and material editing (VQ-NeRF) on Mitsuba 3."""

__version__ = "0.1.0"

import os as _os

# OpenMP threads (torch's CPU kernels) sleep instead of spinning while they wait: with another
# busy process on the machine, spinning threads take its cores and slow both down many times over.
# Only effective when set before torch is first imported; a value already in the environment wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
