"""Sec. 5's two baselines, each a command of its own run on a phase-1 run's frozen world model (tables.py runs them
as columns of the tables): GenRL (genrl.py: a task policy learnt in imagination) and AIME-NoB (aime_nob.py: online
imitation with an OT reward). aime_nob.py shares genrl.py's cell harness (cell_parser, run_cells, load_cell).

    python baselines/genrl.py --demo stickman_run --view side
    python baselines/aime_nob.py --demo stickman_run --view side
"""
