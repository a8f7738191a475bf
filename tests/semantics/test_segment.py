"""2D segmenters for selection: the weight-free feature segmenter and SAM (tiny random model; the
weights lookup and its error)."""
import pytest
import torch

import neumesh_core as nm
from neumesh_core.semantics import FeatureSegmenter, SamSegmenter, SelectConfig, make_segmenter, select_region
from neumesh_core.semantics.segment import find_sam_weights

from .conftest import one_thread, part_clicks


def _view(scene_dir, view):
    cams = nm.load_scene(scene_dir).split("train").cameras
    return cams.K[view], cams.c2w[view], cams.width, cams.height


def test_feature_segmenter_gives_the_clicked_parts_region(multipart_dir, semantic_field):
    from neumesh_core.data import multipart as mp

    field, _ = semantic_field
    view, (x, y) = part_clicks(multipart_dir)[1]   # the head
    K, c2w, w, h = _view(multipart_dir, view)
    with one_thread():
        mask = FeatureSegmenter()(field, (K, c2w, w, h), (x, y))
    assert mask.shape == (h, w) and mask.dtype == bool and mask[int(y), int(x)]
    lab = mp.label_image(K, c2w, w, h)
    assert (lab[mask] == 1).mean() > 0.9 and mask.sum() > 0.6 * (lab == 1).sum()
    assert not FeatureSegmenter()(field, (K, c2w, w, h), (0.5, 0.5)).any()     # background: empty
    with pytest.raises(nm.SelectionError, match="unknown 2D segmenter"):
        make_segmenter("grabcut")


def test_missing_sam_weights_name_the_expected_folder(tmp_path, monkeypatch):
    monkeypatch.setenv("NEUMESH_WEIGHTS", str(tmp_path))
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    with pytest.raises(nm.WeightsUnavailableError) as e:
        make_segmenter("sam")
    assert str(tmp_path / "sam-vit-base") in str(e.value) and "facebook/sam-vit-base" in str(e.value)
    with pytest.raises(ValueError, match="unknown SAM model"):
        find_sam_weights("sam-tiny")


def test_sam_segmenter_plumbing_with_a_tiny_random_model(multipart_dir, semantic_field):
    """Shapes and the selection path only (random weights segment nothing in particular)."""
    tf = pytest.importorskip("transformers")
    from transformers.models.sam.configuration_sam import (SamMaskDecoderConfig, SamPromptEncoderConfig,
                                                           SamVisionConfig)

    torch.manual_seed(0)
    vc = SamVisionConfig(hidden_size=32, num_hidden_layers=2, num_attention_heads=2, mlp_dim=64, output_channels=32,
                         global_attn_indexes=[1], window_size=8, image_size=256, num_pos_feats=16)
    pc = SamPromptEncoderConfig(hidden_size=32, image_size=256, image_embedding_size=16, mask_input_channels=4)
    mc = SamMaskDecoderConfig(hidden_size=32, num_hidden_layers=1, num_attention_heads=2, mlp_dim=64,
                              iou_head_hidden_dim=32)
    model = tf.SamModel(tf.SamConfig(vision_config=vc.to_dict(), prompt_encoder_config=pc.to_dict(),
                                     mask_decoder_config=mc.to_dict()))
    proc = tf.SamProcessor(tf.SamImageProcessor(size={"longest_edge": 256}, pad_size={"height": 256, "width": 256}))
    seg = SamSegmenter(model=model, processor=proc)
    field, _ = semantic_field
    view, xy = part_clicks(multipart_dir)[0]
    K, c2w, w, h = _view(multipart_dir, view)
    with one_thread():
        mask = seg(field, (K, c2w, w, h), xy)
        sel = select_region(field, (K, c2w, w, h), xy, SelectConfig(segmenter=seg))
    assert mask.shape == (h, w) and mask.dtype == bool
    assert len(sel.vertices) > 0 and "segment_pixels" in sel.info
