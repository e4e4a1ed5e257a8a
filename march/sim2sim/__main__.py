from march.sim2sim.runner import main

main()
