"""``python -m march.viz``: runs the tool's command line."""

from march.viz.views import main

main()
