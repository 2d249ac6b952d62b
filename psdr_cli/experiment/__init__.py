"""An experiment loaded whole (the file parsed, its scene read and checked), and a camera dataset's
views in the normalised frame."""
