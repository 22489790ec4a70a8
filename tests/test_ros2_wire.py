"""rmw_zenoh's wire conventions (contracts/ros2_wire.py): names, liveliness tokens, data keys, attachment."""
import struct

import pytest
from tensortouch.contracts import ros2_wire as rw


def test_names_tokens_and_attachment():
    assert rw.name_token("TT-0001") == "TT_0001" and rw.name_token("01.a") == "s01_a"
    q = rw.Qos()
    tok = rw.publisher_token(0, "abc", 0, 3, "/", "n", "/ns/x/wrench", "geometry_msgs/msg/WrenchStamped", "humble", q)
    assert tok == ("@ros2_lv/0/abc/0/3/MP/%/%/n/%ns%x%wrench/geometry_msgs::msg::dds_::WrenchStamped_/"
                   "TypeHashNotSupported/::,10:,:,:,,")
    assert rw.node_token(5, "abc", 0, "/tensortouch", "n") == "@ros2_lv/5/abc/0/0/NN/%/%tensortouch/n"
    assert rw.data_key(5, "/a/b", "sensor_msgs/msg/Image", "kilted").startswith(
        "5/a/b/sensor_msgs::msg::dds_::Image_/RIHS01_d31d41a9")
    gid = rw.gid_of(tok)
    att = rw.attachment(7, 123456789, gid)
    assert len(att) == 33 and att[16] == 16 and struct.unpack_from("<qq", att) == (7, 123456789)
    assert rw.parse_attachment(att) == (7, 123456789, gid)
    with pytest.raises(rw.Ros2Error):
        rw.parse_attachment(att[:-1])
