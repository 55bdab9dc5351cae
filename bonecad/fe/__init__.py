"""Analysis-ready bones: pure functions on a tetrahedral mesh's arrays.

``tets``: the mesh (nodes, elements in gmsh's node order), its node order in
VTK/Abaqus/FEBio, regions along the long axis, end node sets, cross-sections;
``materials``: CT -> density -> Young's modulus integrated over each element,
binned into materials; ``elasticity``: the solver check (scikit-fem) against
beam theory. The mesher (gmsh, global state) is at the edge (``run/tetmesh``),
the file writers in ``export/fe``.
"""
