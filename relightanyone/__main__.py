from relightanyone.cli import main

main()
