"""Process entry points: the command line, the HTTP app, the job store and the scheduler."""
