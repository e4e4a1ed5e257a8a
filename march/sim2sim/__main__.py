"""``python -m march.sim2sim``: runs the tool's command line."""

from march.sim2sim.command_line import main

main()
