"""Log readers: one module per container format, one contract (``readers.base.LogReader``)."""
