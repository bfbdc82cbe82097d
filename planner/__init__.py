"""Pure planning core: process and bead models, slicing, toolpaths, job files. No I/O, no clocks."""
