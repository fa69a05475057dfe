"""Maps: named sets of GPS-tagged images, their features and packed builds."""
