from gtgen.cli import main

main()
