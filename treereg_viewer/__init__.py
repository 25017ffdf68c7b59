"""treereg's browser app (viser): draws stage results, never computes geometry."""
