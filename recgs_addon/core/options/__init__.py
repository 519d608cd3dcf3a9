"""The options of the jobs, each declared once: its flag, help, default, choices and, where the
sidebar shows it, the setting's label and range. The command line's parsers
(``recgs_addon/commands``), the Blender settings (``recgs_addon/blender/properties.py``) and
the generated reference (``tools/make_reference.py``, from those two) are built from here.

The defaults themselves come from the configs they set (``TrainConfig``, ``CausticConfig``)
where a config holds them; a setting whose sidebar default differs from the command line's says
why (``Setting.why``)."""
