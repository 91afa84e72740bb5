"""FastAPI side port: the only package that imports fastapi."""
