"""sfm.viz: the Rerun recording of a run, every stage visible, with a guided tour.

``recorder`` (the stream, its timelines, the tour's texts, the images' thumbnails), one module
per stage's views (``frontend``: extract and match; ``clustering``; ``mapping``; ``merging``;
``models``: cameras, points and the final model), ``graphs`` (graphs drawn in 2D with their
weights), ``tour`` (each stage's markdown text, tied to the paper), ``blueprint`` (the default
layout), ``thumbnails``, ``palette``, ``entities``.  What the recording holds, entity by entity,
is in the README ("The recording").
"""
