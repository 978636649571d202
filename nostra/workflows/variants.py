"""Evaluated policy variants: ids used in metric names, their display labels, imagination modes."""

# imagination modes: closed-loop, oracle MLI / LI (knows the noise window and modalities), AdaMLI
MODES = ("closed", "oracle", "adaptive")

LABELS = {"lstm": "BC-LSTM", "diffusion": "Diffusion Policy", "rssm": "BC-RSSM", "rssm_li": "BC-RSSM + LI",
          "nostra": "BC-NOSTRA", "nostra_mli": "BC-NOSTRA + MLI", "nostra_adamli": "BC-NOSTRA + AdaMLI"}
