"""The X-ray settings a user may override and the words both front ends show them in (the window's Register step,
``panels.registration_panel``; the Slicer module's Inputs, ``CarmReg.py``): (key, words) pairs, the first the
default, auto. The keys are ``RegistrationParameters``' values (``image.appearance.POLARITY_SETTINGS``,
``image.prepare.STORAGE_SETTINGS``, ``image.field.FIELDS``; a test pins them). Qt-free."""

POLARITY_CHOICES = (("auto", "Find from the image"), ("bone-dark", "Bone dark (fluoroscopy)"),
                    ("bone-bright", "Bone bright (radiograph)"))
"""The X-ray polarity settings (``RegistrationParameters.polarity``) and their words."""
STORAGE_CHOICES = (("auto", "As the file states, else found"), ("log-display", "Log display (processed)"),
                   ("linear-intensity", "Linear intensity (raw detector)"))
"""The X-ray storage settings (``RegistrationParameters.storage``) and their words."""
FIELD_CHOICES = (("auto", "Found from the image"), ("whole", "The whole image"))
"""The X-ray field settings (``RegistrationParameters.xray_field``) and their words."""
