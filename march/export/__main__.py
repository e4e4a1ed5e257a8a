"""``python -m march.export``: runs the tool's command line."""

from march.export.bundle import main

main()
