"""Faults as plug-ins: one small class per fault family (``base.Fault``), parameterised (a sensor
bias is one class for every sensor and magnitude), registered in one table
(``registry.FAULTS``). A family names the node path it breaks (``node``: the plant's transmit
path, its receiver, its hardware, the driver app, an outside bus client, a configuration file),
implements the hook of that path, and says how it is judged (``Fault.judge``).

The nodes call the hooks through :class:`~hil.faults.injector.Injector` at fixed points of
their tick (before and after the plant sends, when it receives a command, when its bridge acts,
before the app answers); the compiled SIL loop hands a fault's window and a margin around it to
the node objects (``Injector.spans``). A family uses the nodes' public methods only.

To add a family: a class in a new module of this package, and its instances in
``registry.FAULTS`` (``spike.py`` is the example: one file, one registry line)."""
