"""Empty stand-ins for modules the model gym imports but its NSS data and training path never calls.

Put this folder on PYTHONPATH (benchmarks/check_nss_consumer.sh, benchmarks/gpu/nss_gym_step.sh); NGMG_STUBS names
the top-level modules to stub (default "executorch torchvision pyiqa"):
- executorch 1.2.0: the gym's model export (VGF); it does not import against another torch than 2.11, and its
  wheel is too large to carry to the GPU machine;
- pyiqa: only the ST-LPIPS metric, which the NSS template does not list (its dependencies are gigabytes);
- torchvision: only where the torch reused is not the one torchvision was built for (BlendSR's venv): torcheval
  imports it for FID, lpips builds its AlexNet from it and the NSS dataset flips with it. The stand-in's
  models.alexnet is torchvision's AlexNet feature stack with random weights only (pretrained weights cannot be had
  without torchvision's download), and transforms.functional.hflip/vflip flip a tensor's last/second-last dim.
"""
import importlib
import importlib.abc
import importlib.machinery
import os
import sys
import types

STUBBED = tuple(os.environ.get("NGMG_STUBS", "executorch torchvision pyiqa").split())


def _alexnet(pretrained=False, weights=None, **_):
    """torchvision's AlexNet layer stack (features only), random weights: lpips's pnet_rand=True backbone."""
    if pretrained or weights is not None:
        raise RuntimeError("torchvision is stubbed (NGMG_STUBS): no pretrained AlexNet; use pnet_rand=True")
    from torch import nn

    model = nn.Module()
    model.features = nn.Sequential(
        nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2))
    return model


# torchvision.transforms.functional's flips of a tensor (the NSS dataset's GT augmentation): the last two dims
_FLIPS = {"hflip": lambda img: img.flip(-1), "vflip": lambda img: img.flip(-2)}


class _Any(types.ModuleType):
    __path__ = []

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        if self.__name__ == "torchvision" and name == "models":
            return importlib.import_module("torchvision.models")
        if self.__name__ == "torchvision.models" and name == "alexnet":
            return _alexnet
        if self.__name__ == "torchvision.transforms" and name == "functional":
            return importlib.import_module("torchvision.transforms.functional")
        if self.__name__ == "torchvision.transforms.functional" and name in _FLIPS:
            return _FLIPS[name]
        return type(name, (), {"__init__": lambda self, *a, **k: None, "__call__": lambda self, *a, **k: None})


class _Stubs(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in STUBBED:
            return importlib.machinery.ModuleSpec(name, self, is_package=True)
        return None

    def create_module(self, spec):
        return _Any(spec.name)

    def exec_module(self, module):
        pass


sys.meta_path.insert(0, _Stubs())
