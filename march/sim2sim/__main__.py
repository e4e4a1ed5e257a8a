from march.sim2sim.command_line import main

main()
