"""The product's own files, shipped in the wheel as ``carmreg.resources``: the sample case, C-arm presets, icons.

Read them through ``carmreg.logic.resources`` (``importlib.resources``), never by a path relative to the source.
"""
