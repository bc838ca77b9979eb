"""Ingestion: every input is checked once, at the boundary, before anything is stored or queued.

- crowdbake.ingest.uploads: an uploaded file against its format and the bake's needs (UploadRejected
  with one FieldError per problem: field, file, where);
- crowdbake.ingest.bake_request: a bake request against what its assets' uploads measured.

The validate stage (crowdbake.stages.validate) checks the same files again in the worker, where they
are parsed once and copied into the work folder.
"""
