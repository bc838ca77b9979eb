"""Readers and writers of the input formats (glTF, PC2, OBJ) and of bundles (shared_formats v1)."""
