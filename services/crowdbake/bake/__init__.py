"""Pure bake functions over numpy arrays: no file, network or GL I/O here."""
