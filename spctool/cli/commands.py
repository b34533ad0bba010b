"""The table of spctool's commands: each command's name and the module that registers it.

Kept apart from :mod:`spctool.cli.main` (the click group that imports a command's module when it
runs) so that shell completion (:mod:`spctool.cli.completion`) can list the commands without
importing the group; nothing is imported here.
"""

#: every command and the module whose ``register(cli)`` adds it, in --help order (mission stages
#: first); a test checks this table against what the modules register
COMMANDS = {
    "lithos-select": "spctool.cli.select",
    "predict": "spctool.cli.appearance",
    "extract": "spctool.cli.appearance",
    "correlate": "spctool.cli.register",
    "register": "spctool.cli.register",
    "solve-pose": "spctool.cli.pose",
    "navigate": "spctool.cli.navigate",
    "geometry": "spctool.cli.geometry",
    "lithos": "spctool.cli.heights",
    "info": "spctool.cli.files",
    "validate": "spctool.cli.files",
    "convert": "spctool.cli.files",
    "project": "spctool.cli.project",
    "simulate": "spctool.cli.sim",
    "make-maplets": "spctool.cli.sim",
    "render": "spctool.cli.sim",
    "demo": "spctool.cli.sim",
    "montecarlo": "spctool.cli.montecarlo",
    "batch": "spctool.cli.batch",
    "warmup": "spctool.cli.jit",
    "man": "spctool.cli.manpages",
}
#: the command modules, in --help order
COMMAND_MODULES = tuple(dict.fromkeys(COMMANDS.values()))
