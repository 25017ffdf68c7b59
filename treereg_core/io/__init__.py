"""Files: scans in and out, transform files, case folders, and the atomic writer every write goes through."""
