"""`python -m vq_mitsuba.cli ARGS` runs `vq-mitsuba ARGS`; `--manual` alone prints docs/cli.md."""

import sys

from vq_mitsuba.cli import main, manual

if sys.argv[1:] == ["--manual"]:
    print(manual(), end="")
    sys.exit(0)
sys.exit(main())
