"""Add-on preferences: where the BlendSR library lives and which Python runs inference when Blender's has no torch."""
from __future__ import annotations

import bpy
from bpy.props import EnumProperty, StringProperty

from . import library

ADDON_ID = __package__


def _library_changed(self, context):
    library.status(self.library_path, refresh=True)


class BlendSRPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_ID

    library_path: StringProperty(
        name="Library path", subtype="DIR_PATH", default="", update=_library_changed,
        description="A virtual environment, site-packages folder or BlendSR checkout to add to Blender's sys.path "
                    "when the blendsr library is not installed in Blender's Python")
    python_path: StringProperty(
        name="External Python", subtype="FILE_PATH", default="",
        description="A Python interpreter with torch and blendsr[train], used for preview inference when "
                    "Blender's Python has no torch")
    inference: EnumProperty(
        name="Inference", default="AUTO",
        items=(("AUTO", "Automatic", "Torch in Blender's Python when it imports there, else ONNX Runtime (the "
                                     "extension's graphs of the shipped networks), else the external Python"),
               ("INTERNAL", "Blender's Python", "Always in Blender's Python (needs torch there)"),
               ("EXTERNAL", "External Python", "Always with the external Python (keeps torch out of Blender)"),
               ("ONNX", "ONNX Runtime", "Always the ONNX graphs the extension carries, through its onnxruntime, in "
                                        "Blender's Python (no torch; shipped networks and non-learned models)")),
        description="Where the preview runs the model")

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "library_path")
        st = library.status(self.library_path)
        if st.ok:
            layout.label(text=f"Library: {st.root} (torch {'found' if st.torch else 'not found'}, ONNX Runtime "
                              f"{'found' if st.onnxruntime else 'not found'})", icon="CHECKMARK")
        else:
            box = layout.box()
            box.label(text=st.message, icon="ERROR")
            for line in st.hint:
                box.label(text=line)
        layout.prop(self, "inference")
        layout.prop(self, "python_path")


class Prefs:
    """Preference values, also when the add-on is registered without being enabled (no preferences entry)."""

    def __init__(self, context=None):
        context = context or bpy.context
        addon = context.preferences.addons.get(ADDON_ID)
        p = addon.preferences if addon is not None else None
        self.library_path = getattr(p, "library_path", "") if p is not None else ""
        self.python_path = getattr(p, "python_path", "") if p is not None else ""
        self.inference = getattr(p, "inference", "AUTO") if p is not None else "AUTO"


CLASSES = (BlendSRPreferences,)


register, unregister = bpy.utils.register_classes_factory(CLASSES)
