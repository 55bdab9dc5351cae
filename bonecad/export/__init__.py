"""Exporters: the files written from stage results (STEP, IGES, JSON, the report), by kind and
format (``bonecad.export.registry``)."""
