"""``python -m march.bench``: runs the tool's command line."""

from march.bench.command import main

main()
