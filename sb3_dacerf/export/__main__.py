"""``python -m sb3_dacerf.export``: the command line of :mod:`sb3_dacerf.export.cli`."""

from sb3_dacerf.export.cli import main

main()
