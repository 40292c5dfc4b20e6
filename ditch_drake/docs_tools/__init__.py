"""Tools that make the documentation: the DWA baseline page, figures, browser screenshots."""
