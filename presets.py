"""Sec. 5's scale and ours: the presets of every command side by side (smoke: seconds, for the tests; cpu: the defaults;
paper: the paper's sizes, for a GPU).

DATA  where each preset's datasets go by default (--data): the smoke preset's 20-step episodes never share a folder with
      the 500-step ones of the others (cpu and paper episodes are alike: paper's D_body extends cpu's)
"""
import os

DATA = {"smoke": os.path.join("data", "smoke"), "cpu": "data", "paper": "data"}
