"""What a run shows a person: the report, the index page, figures."""
