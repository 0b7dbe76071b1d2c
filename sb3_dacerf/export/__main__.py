"""``python -m sb3_dacerf.export``: see :func:`sb3_dacerf.export.main`."""

from sb3_dacerf.export import main

main()
