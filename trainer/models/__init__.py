"""The networks of the zoo and the LPIPS net, one module each (the V2V paper's networks, Lou et al.,
NeurIPS 2025, reimplemented with the authors' parameter names so their checkpoints load):

* :mod:`.layers`: the shared event_cnn_minimal layers and the driver's input padding (``pad_input``);
* :mod:`.e2vid`: E2VID (``E2VIDRecurrent``) and E2VID++ (``E2VIDPlusPlus``);
* :mod:`.evflow`: EV-FlowNet (``EVFlowNet`` over a head-less ``UNet``);
* :mod:`.hypere2vid`: HyperE2VID; :mod:`.etnet`: ETNet; :mod:`.eraft`: E-RAFT;
* :mod:`.lpips`: LPIPS v0.1 (VGG16 / AlexNet), the reconstruction loss's perceptual term.

``trainer.zoo.build_model`` builds a network by task name from its config section.
"""
from .e2vid import E2VIDPlusPlus, E2VIDRecurrent
from .eraft import ERAFT
from .etnet import ETNet
from .evflow import EVFlowNet, UNet
from .hypere2vid import HyperE2VID
from .layers import PAD_MULTIPLE, ConvLSTM, RecurrentConvLayer, pad_input

__all__ = ["PAD_MULTIPLE", "pad_input", "ConvLSTM", "RecurrentConvLayer", "E2VIDRecurrent", "E2VIDPlusPlus", "UNet",
           "EVFlowNet", "HyperE2VID", "ETNet", "ERAFT"]
