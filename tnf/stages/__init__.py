"""One module per ``tnf`` stage; each exposes ``run(cfg)``, called by the Hydra app in ``tnf.cli``."""
