#!/usr/bin/env python
"""Does a capture's brightness follow its camera? Reads the highlight evidence the way a fit does
(`vq_mitsuba.engine.evidence`, before the first step) and, per hit, the rank correlation between its
luminance in the views that see it and the cosine between each view and the hit's normal.

    python benchmarks/view_brightness.py OUT.json LABEL -- FIT ARGUMENTS
    python benchmarks/view_brightness.py res.json dtu24 -- /data/dtu_scan24 --downscale 4 --mesh MESH

Under a lamp at the camera a matte surface brightens as the view faces it (correlation near +1);
under a static light its brightness does not depend on the view (near 0). The fit runs its start-up
up to the evidence reading in a scratch folder, then stops. Adds LABEL's figures, with the
command, commit, machine and versions, to OUT.json.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from provenance import provenance, write_json


class _Read(BaseException):  # past the command's own error handling
    pass


def main(argv: list[str]) -> int:
    if len(argv) < 3 or argv[2] != "--":
        print(__doc__)
        return 2
    out, label, fit_args = Path(argv[0]), argv[1], argv[3:]
    from vq_mitsuba.cli import main as cli_main
    from vq_mitsuba.engine import evidence

    original, record = evidence.sample_views, {}

    def reading(scene, capture, positions, normals, *args, **kwargs):
        views = original(scene, capture, positions, normals, *args, **kwargs)
        p = positions.detach().cpu().double().numpy()
        n = normals.detach().cpu().double().numpy()
        valid = views.valid.numpy()
        origins = np.array([cam.origin for cam in capture.cameras])[np.maximum(views.view.numpy(), 0)]
        to_cam = origins - p[:, None]
        cos = (to_cam / np.linalg.norm(to_cam, axis=-1, keepdims=True) * n[:, None]).sum(-1)
        rho = evidence.rank_correlation(cos, views.lum.numpy(), valid)
        shown = ~np.isnan(evidence.highlight_tint(views).numpy())
        record.update({"hits": int((~np.isnan(rho)).sum()), "hits_with_highlight": int(shown.sum()),
                       "rho_median": float(np.nanmedian(rho)),
                       "rho_median_with_highlight": float(np.nanmedian(rho[shown])) if shown.any() else None,
                       "share_rho_above_0.5": float(np.nanmean(rho > 0.5))})
        raise _Read

    evidence.sample_views = reading
    with tempfile.TemporaryDirectory() as scratch:
        try:
            cli_main(["fit", *fit_args, "-o", str(Path(scratch) / "run"), "--quiet"])
        except _Read:
            pass
    if not record:
        print("the fit ended before reading the evidence (is loss.prior_evidence auto?)", file=sys.stderr)
        return 1
    print(label, json.dumps(record))
    data = json.loads(out.read_text()) if out.is_file() else {"captures": {}}
    data["captures"][label] = {**provenance(), **record}
    write_json(out, data)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
