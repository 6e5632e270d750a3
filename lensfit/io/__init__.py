"""What users hand over and what lensfit reads back: images (PNG, TIFF, JPEG, DNG, camera RAW) and
their EXIF, stack.toml and its draft, the data_specs files, sensor formats, the samples table, and the
budgets checked before anything large is read."""
