from march.export.bundle import main

main()
