"""`calib` and `python -m calib_cli`: the command line, with the commands'
modules imported on demand (calib_cli.cli.main._Commands)."""


def run() -> None:
    import os

    if "_CALIB_COMPLETE" in os.environ:  # shell completion: from the static tree, < 0.3 s
        from calib_cli.cli.index import stub

        stub().main(prog_name="calib")
        return
    import calib_cli.cli as pkg

    pkg.LAZY_COMMANDS = True
    from calib_cli.cli.main import main

    main()


if __name__ == "__main__":
    run()
