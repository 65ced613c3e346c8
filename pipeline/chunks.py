"""How many points a reader decodes at a time: what bounds its memory, whatever the
block's size. Plain constants, so the run options take their default without numpy."""

#: points read from a block at a time (bounded memory)
CHUNK_POINTS = 2_000_000
