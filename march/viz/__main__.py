from march.viz.views import main

main()
