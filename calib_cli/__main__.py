"""`calib` and `python -m calib_cli`: the command line, with the commands'
modules imported on demand (calib_cli.cli.main._Commands)."""


def run() -> None:
    import gc
    import os

    # the start-up imports (click, numpy, h5py, pyarrow, ...) allocate some 10^5 objects
    # that live as long as the process: with the default threshold (700) the cyclic
    # collector runs hundreds of times over them, about 30 ms of every command's start-up;
    # every 10000 allocations it still collects any cycle a command leaves behind
    gc.set_threshold(10_000, 10, 10)

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
