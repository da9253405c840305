"""`python -m recon_rgbd <command> …` (also the `recon-rgbd` console script): the `recon` CLI's
`infer`, `scene`, `serve`, `synth`, `eval` and `weights` commands, run by the extension itself
(the binary's argument parser, code, messages and exit codes; a wheel carries no binary)."""

import os
import signal
import sys

from ._recon import cli_main


def main(argv=None):
    """Runs `argv` and returns the exit status; without `argv`, this process's arguments, as
    a program (usage lines name `python -m recon_rgbd` or the console script's name)."""
    if argv is not None:
        return cli_main(["python -m recon_rgbd", *argv])
    started = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ""
    prog = "python -m recon_rgbd" if started in ("", "__main__.py", "-c") else started
    # Ctrl-C as for the binary: Python's own handler would only set a flag while the command
    # runs without the GIL (`serve` installs its graceful handler over this default).
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    return cli_main([prog, *sys.argv[1:]])


if __name__ == "__main__":
    sys.exit(main())
