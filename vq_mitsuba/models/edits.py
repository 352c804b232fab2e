"""The older name of `vq_mitsuba.models.material_edits`, kept for imports not yet moved to it."""

import sys

from vq_mitsuba.models import material_edits

sys.modules[__name__] = material_edits
