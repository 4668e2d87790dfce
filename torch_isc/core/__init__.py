"""The core structures: packed mesh batches, implicit curves on them, point location and
zero-set extraction. No file, image or command-line code is imported here."""
