"""Scene formats: 3DGS PLY, COLMAP, nerfstudio transforms.json, ScanNet++, scene folders.

Everything here returns NumPy; kernels take it from there.
"""
