"""``python -m hil.hub -p PORT``: the bench's CAN hub started by hand (the command the docs and
``hil run`` use; the hub itself is :mod:`hil.transport.hub`)."""

from hil.transport.hub import main

if __name__ == "__main__":
    raise SystemExit(main())
