"""What a run leaves behind: rendered and caustic-free images (``exports``), the Markdown
report (``report``) and its charts (``plot``)."""
