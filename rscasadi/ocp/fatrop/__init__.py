"""fatrop from C: the driver that calls it with the condensed NLP, and BLASFEO for its linear algebra."""
