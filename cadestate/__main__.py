from cadestate.cli import main

main()
