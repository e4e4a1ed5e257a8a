from march.bench.env_speed import main

main()
