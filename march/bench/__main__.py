from march.bench.command import main

main()
