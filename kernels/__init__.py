"""Warp kernels of the engine (installed as `perch_warp.kernels`); the demo's and bench's own
kernels sit beside their callers (perch_warp/photo_kernels.py, perch_warp/bench/kernels.py).

render   -- kernel #1: ray-cast the textured mesh for a batch of candidate poses (BVH form),
            and the MeshLook (appearance), PixelRays and RenderedBoxes (kernel #1's output) structs.
raster   -- kernel #1's raster form: each triangle tests the pixel rays it covers.
features -- kernel #2: AlexNet-conv1 features of the composited candidate and its
            rarity-weighted cosine similarity with the photo's features; the PointLayout struct
            (candidates' feature points) that kernel #2, the bound and the raster silhouette share.
boxes    -- candidates' pixel boxes: the mesh's hull points projected for each pose.
reduce   -- the top-α mean of each candidate's feature-point scores (one float back per candidate).
bound    -- the pruned search's silhouette bound (the BVH form's any-hit silhouette, the ceiling map at hits).
"""
