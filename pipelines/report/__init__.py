"""The HTML report behind ``relightanyone report``: page building, assets, sheets, metrics, browser check."""
