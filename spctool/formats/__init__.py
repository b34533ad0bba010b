"""SPC files and photos <-> plain dataclasses (no numerics beyond decoding).

One module per file type; each offers a dataclass, ``read_*`` / ``parse_*`` and
``write_*`` / ``format_*``.  See ``shared/docs/spc-formats.md``.
"""
