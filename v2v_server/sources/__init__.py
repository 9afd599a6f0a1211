"""Where a video's bytes come from: a folder, a list file or metadata table, an object store, tar
shards and zip parts, segments of long videos; each listed as sample-id paths, opened for
decoding, and named by an identity (``source.VideoSource``). Nothing here knows what is made of
the bytes: the frames side (``v2v_server.frames``) takes a source."""
