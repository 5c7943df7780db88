from calib_cli.cli.main import main

main()
