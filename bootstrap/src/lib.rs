//! s3res-bootstrap library: the system description and the launcher.
