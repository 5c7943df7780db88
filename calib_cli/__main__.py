"""`calib` and `python -m calib_cli`: the command line, with the commands'
modules imported on demand (calib_cli.cli.main._Commands)."""


def _command(args) -> str | None:
    """The subcommand's name: the first argument that is not an option."""
    return next((a for a in args if not a.startswith("-")), None)


def run() -> None:
    import gc
    import os
    import sys

    import calib_cli.cli as pkg

    # the start-up imports (click, numpy, h5py, pyarrow, ...) allocate some 10^5 objects
    # that live as long as the process: with the default threshold (700) the cyclic
    # collector runs hundreds of times over them, about 30 ms of every command's start-up;
    # every 10000 allocations it still collects any cycle a command leaves behind
    gc.set_threshold(10_000, 10, 10)
    if _command(sys.argv[1:]) == "import":
        # no linear algebra in an import: OpenBLAS's thread pool, started by the first
        # numpy import, only costs its start and spin (~50 ms CPU of an import of 1 s)
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
        # no collection at all until the import command has its modules (it turns the
        # collector on again then, cli/cmd_import.py:_started; a usage error exits first)
        gc.disable()
        pkg.GC_DEFERRED = True

    if "_CALIB_COMPLETE" in os.environ:  # shell completion: from the static tree, < 0.3 s
        from calib_cli.cli.tree import stub

        stub().main(prog_name="calib")
        return
    from calib_cli.cli.tree import help_from_tree

    if help_from_tree(sys.argv[1:]):  # `calib X --help`: from the static tree, < 0.5 s
        return
    pkg.LAZY_COMMANDS = True
    from calib_cli.cli.main import main

    main()


if __name__ == "__main__":
    run()
