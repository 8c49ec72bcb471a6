"""Writers and readers of other projects' dataset layouts (Arm's NSS capture layout).

Every convention conversion between BlendSR and those layouts is in ``formats/conventions.py``; the layouts'
files and JSON in one module each (``formats/nss.py``). Pure numpy + json + OpenEXR: no bpy, no torch.
"""
