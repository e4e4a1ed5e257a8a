from march.audit.command import main

main()
