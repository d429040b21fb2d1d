"""The application: the ``omg4`` command (:mod:`omg4.app.cli`, one thin module per subcommand in
:mod:`omg4.app.commands`), the demo and ``omg4 bench`` runs with their tables and plots (:mod:`~omg4.app.demo`,
:mod:`~omg4.app.bench`, :mod:`~omg4.app.report`), the browser viewer (:mod:`~omg4.app.viewer`), the checks of
output paths (:mod:`~omg4.app.outputs`) and the ``--nproc`` launcher (:mod:`~omg4.app.launch`). It may import
every library package; no library module imports it.
"""
