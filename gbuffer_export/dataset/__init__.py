"""Datasets: many clips from one spec (pure Python). ``spec`` parses and expands a spec, ``build`` renders it on an
executor and keeps the index, ``check`` validates a dataset, ``buffers`` maps models to the buffers they read."""
