"""GraspNet-1Billion / SuctionNet-1Billion layout: read its views as ParcelPick records, write ours in it.

- ``reader.read_view(root, scene, camera, ann_id)``: one view -> a record with ``dataset/annotate.py``'s keys.
- ``writer.write_records(records, root)``: ParcelPick records -> a miniature SuctionNet-format tree.
- ``convert.import_views(...)``: views -> HDF5 shards that the torch Dataset, trainers and ``eval/ap.py`` open.
- ``models.world_meshes(record)``: the SuctionNet models of a record, posed, for re-scoring.
- ``python -m dataset.suctionnet {import,export}``: the two conversions from the command line.

The layout, the mapping and their sources: docs/suctionnet_layout.md.
"""
