"""The renderer's named modes (the lists :class:`spctool.stages.render.RenderOptions` accepts), in a
module of their own so that an options check (register's ``template_shading`` and
``template_visibility``) needs no import of the renderer and its kernels (~0.04 s of every maplet-space
command's start, issue 42).  Specification: as :mod:`spctool.stages.render` (README "Template
shading").
"""

#: shading normals of height patches (:class:`spctool.stages.render.RenderOptions`)
SHADINGS = ("smooth", "facet", "gouraud")

#: how a one-patch window finds each sub-ray's terrain (:class:`spctool.stages.render.RenderOptions`)
VISIBILITIES = ("march", "raster")

#: node slopes a smooth-shaded patch interpolates (:data:`spctool.geometry.heightfield.NODE_SLOPES`,
#: named here for the same reason; a test keeps the two equal)
NODE_SLOPES = ("spc", "fourth")
