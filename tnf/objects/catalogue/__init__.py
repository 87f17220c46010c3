"""The built-in objects' makers, one module per family; ``tnf.objects.builtin`` names them (``MAKERS``)."""
