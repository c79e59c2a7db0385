"""Image and metadata input/output: pixels in linear light, EXIF, metadata carried into outputs, DNG opcodes."""
