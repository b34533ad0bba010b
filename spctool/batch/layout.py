"""The names of a batch's output layout (spctool.batch package docstring), shared by the batch and the
landmark refinement that reads a batch's outputs (:mod:`spctool.batch.refine`) without importing it."""

#: the folder of a batch's landmark tables (<PIC>.select.txt, .register.txt, .pose.txt, .done.json)
TABLES_DIR = "TABLES"
