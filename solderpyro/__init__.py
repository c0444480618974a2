"""solderpyro."""
